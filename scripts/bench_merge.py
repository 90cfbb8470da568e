"""The driver's final merge after a Ray extraction: `--ray-merge copy` against `--ray-merge virtual`.

Takes the images of a real feature file (e.g. 640 px SEKD, 2,000 keypoints: ~1 MB per
image), repeats them under new keys up to N images, writes them as Ray workers do (tasks of
--task images, 4 by default: part chunks for ``copy``, shard files and their descriptions
for ``virtual``; one process here, spread over the workers in a run), then times the
driver's merge into ``features.h5`` (``partstore.merge_parts``: copy + fsync + rename, as
at the end of a run; for ``virtual`` the workers' descriptions saved as a manifest first,
as the driver does) and checks that the files read the same arrays. ``virtual`` copies the groups each shard holds ready-made
(``shards.LINKS``); ``virtual-described`` is the same merge from shards without them, so each
group is built from the workers' descriptions (shards of older versions). Prints images/s
and MB/s of each side, and the file sizes. The page cache is dropped before each merge
when run as root (so the merge reads from disk as after a real run on shared storage);
`--keep-cache` skips that.

Usage: python scripts/bench_merge.py FEATURES.h5 [--images 2000] [--task 4] [--work DIR]
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from sekd_sfm.files import features as ff
from sekd_sfm.files import partstore, shards


def _drop_cache(keep: bool) -> str:
    if keep or os.geteuid() != 0:
        return "page cache kept"
    os.sync()
    try:
        Path("/proc/sys/vm/drop_caches").write_text("3\n")
        return "page cache dropped"
    except OSError:
        return "page cache kept (cannot drop it here)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("features", type=Path)
    parser.add_argument("--images", type=int, default=2000)
    parser.add_argument("--work", type=Path, default=None)
    parser.add_argument("--keep-cache", action="store_true")
    parser.add_argument("--task", type=int, default=4,
                        help="images per Ray task, i.e. per shard (execution.task_size: 4 up to 32 workers, 64 at 512)")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_merge"))
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    source = [(k, ff.read_features(args.features, k)) for k in ff.list_keys(args.features)]
    items = [(f"r{i // len(source)}/{source[i % len(source)][0]}", source[i % len(source)][1])
             for i in range(args.images)]
    mb = sum(a.nbytes for _, arrays in items for a in arrays.values()) / 1e6
    with h5py.File(args.features, "r") as f:
        attrs = dict(f.attrs)
    print(f"merge: {len(items)} images ({len(source)} distinct), {mb:.0f} MB ({mb / len(items):.2f} MB each), "
          f"tasks of {args.task}")
    rates = {}
    for mode in ("copy", "virtual", "virtual-described"):
        out = work / mode / "features.h5"
        out.parent.mkdir()
        partstore.create_empty(out, attrs)
        described = {}
        t0 = time.perf_counter()
        for start in range(0, len(items), args.task):
            task = items[start:start + args.task]
            if mode == "copy":
                parts = partstore.PartStore(out, max_items=args.task + 1, max_seconds=1e9, writer="bench")
                for key, arrays in task:
                    parts.save(key, arrays)
                parts.flush()
            else:  # a worker writes its shard and describes it (shapes, dtypes) for the driver
                shard, description = shards.write_shard(out, task, ff.write_image_group, "bench")
                described[shard.name] = description
                if mode == "virtual-described":
                    with h5py.File(shard, "a") as f:
                        del f[shards.LINKS]
        t1 = time.perf_counter()
        cache = _drop_cache(args.keep_cache)
        t2 = time.perf_counter()
        if described:  # the driver's side: the workers' descriptions saved, then the merge
            shards.write_manifest(out, described)
        merged = partstore.merge_parts(out, partstore.PartStore(out))
        t3 = time.perf_counter()
        assert merged == len(items), (mode, merged)
        rates[mode] = len(items) / (t3 - t2)
        print(f"{mode:17s} workers' writes {len(items) / (t1 - t0):7.0f} images/s "
              f"({mb / (t1 - t0):5.0f} MB/s, one process)"
              f" | driver's merge {rates[mode]:7.0f} images/s ({mb / (t3 - t2):6.0f} MB/s; {cache})"
              f" | features.h5 {os.path.getsize(out) / 1e6:8.1f} MB")
    copy = work / "copy/features.h5"
    for other in ("virtual", "virtual-described"):
        for key in (items[0][0], items[-1][0]):
            a, b = ff.read_features(copy, key), ff.read_features(work / other / "features.h5", key)
            assert all(np.array_equal(a[n], b[n]) for n in a), (other, key)
    print(f"merge rate: virtual / copy {rates['virtual'] / rates['copy']:.1f}x, virtual / virtual-described "
          f"{rates['virtual'] / rates['virtual-described']:.1f}x; the files read the same arrays")
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
