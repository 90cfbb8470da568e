"""Training configuration: one flat dataclass, named schedules (YAML in ``configs/``), overrides.

Every hyper-parameter of docs/method.md "Training" is a field; where the paper and the authors'
code disagree, the field chooses (see ``docs/training.md``). Resolution order:
schedule YAML -> user YAML file -> explicit overrides (``--rounds``, ``--set key=value``).
"""
from __future__ import annotations

import dataclasses
import math
import os
import typing
from dataclasses import asdict, dataclass, field
from pathlib import Path

import yaml

from ..errors import SekdError

CONFIG_DIR = Path(__file__).parent / "configs"
SCHEDULES = ("paper", "cpu", "tiny")
#: Fields that may change when a run is resumed: they pick hardware, not results.
RUNTIME_FIELDS = ("device", "num_threads", "num_workers", "progress")

CHOICES = {
    "desc_loss": ("ratio", "margin"),
    "margin_normalise": ("count", "nonzero"),
    "det_preserve_on": ("logits", "prob"),
    "rep_loss": ("weighted", "paper"),
    "label_warp": ("forward", "inverse"),
    "best_metric": ("mma3", "ha_avg"),
    "device": ("auto", "cpu", "cuda"),
    "train_precision": ("fp32", "bf16", "auto"),
    "lr_schedule": ("plateau", "halfway"),
}


@dataclass
class TrainConfig:
    """All settings of a training run. Units: pixels of the resized training image unless stated."""

    # --- run --------------------------------------------------------------------------
    schedule: str = "cpu"            # name of the base schedule (informational once resolved)
    images: str = ""                 # training image folder
    init_weights: str = ""           # start checkpoint; "" = random init seeded by `seed`
    seed: int = 0
    device: str = "auto"             # auto = CUDA when present
    num_threads: int = 0             # CPU intra-op threads per process; 0 = all cores / processes
    num_workers: int = 0             # DataLoader worker processes for training pairs
    progress: bool = True            # tqdm bars
    cache_images: bool = True        # keep the resized RGB images of a step in memory
    keep_epoch_checkpoints: bool = True
    save_maps: bool = False          # also store the float16 score maps (Pbar, R) with the labels
    fast_deconv: bool = True         # grouped transposed convs as block-diagonal dense ones (same maths, faster on CPU)
    train_precision: str = "fp32"    # training steps (b), (d): bf16 = mixed precision (bf16 autocast, fp32 weights and
    #                                  losses); auto = bf16 where the device computes bf16 natively; labels stay fp32
    # --- outer loop (docs/method.md "Training") -------------------------------------
    rounds: int = 5
    subset_factor: int = 2           # round k uses images i with i mod S == k mod S
    round0_random: bool = False      # [paper] round 0 = random keypoints (a0) + (b); False = [code]: (c), (d) only
    random_keypoints: int = 250      # a0: uniform random pixels per image (with replacement)
    random_score: float = 0.5        # a0: score-map value
    alpha_round0: float = 0.0        # detector-preservation weight in (b) after random keypoints
    # --- data (§1) --------------------------------------------------------------------
    long_side: int = 320             # resize so the long side <= this (0 = keep); then crop to size_multiple
    size_multiple: int = 16
    jitter_target: bool = True       # [code] jitter the unwarped view too; [paper] original image
    brightness: list[float] = field(default_factory=lambda: [0.6, 1.4])
    contrast: list[float] = field(default_factory=lambda: [0.6, 1.4])
    saturation: list[float] = field(default_factory=lambda: [0.6, 1.4])
    hue: list[float] = field(default_factory=lambda: [-0.2, 0.2])
    rotation_deg: list[float] = field(default_factory=lambda: [-40.0, 40.0])
    shear_deg: list[float] = field(default_factory=lambda: [-40.0, 40.0])
    scale: list[float] = field(default_factory=lambda: [0.7, 1.4])
    isotropic_scale: bool = False    # [code] sx, sy drawn independently; True: one draw for both
    translation: list[float] = field(default_factory=lambda: [-0.04, 0.04])  # normalised units
    perspective: float = 0.0         # training pairs: projective terms up to this (normalised units); 0 = affine, the spec
    label_warp: str = "forward"      # forward = paper's Y^ = H(Y); inverse = the code's defect
    crop_height: int = 192
    crop_width: int = 192
    batch_size: int = 4              # global: split evenly over distributed processes
    # --- labelling (§3, §5) -------------------------------------------------------------
    num_warps: int = 4               # m
    border_band: int = 14            # (a): detector output ignored this close to a warped view's border
    nms_radius: int = 3
    max_keypoints: int = 500
    det_threshold: float = 0.46
    rel_threshold: float = 0.85
    rel_min_keypoints: float = 0.0   # lower rel_threshold for a step whose labels average fewer (0: fixed)
    det_border_factor: float = 1.0   # (a): drop keypoints closer than factor * nms_radius to a border
    rel_border_factor: float = 4.0   # (c): same, 4r in the code
    rel_radius: int = 3              # distinctness neighbourhood, map pixels (lattice -3..3)
    rel_stride: int = 2              # lattice step, map pixels
    rel_rep_eps: float = 0.03        # r = Ddis / (Drep + eps)
    rel_dist_eps: float = 1.0e-4     # dist = sqrt(2 - 2 f.g + eps)
    rel_count_eps: float = 0.01      # R = sum r_k / (sum v_k + eps)
    label_chunk: int = 8             # views per labelling forward (memory bound)
    # --- step (b): descriptor (§4) -------------------------------------------------------
    epochs_desc: int = 4
    desc_loss: str = "ratio"         # [code] ratio form; [paper] margin form
    ratio_threshold: float = 0.85
    margin: float = 0.8
    margin_normalise: str = "count"  # [paper] 1/n; "nonzero" = the code's optional variant
    neg_min_distance: float = 0.008  # negatives closer than this count as the same point
    neg_self_penalty: float = 10.0
    neg_min_pixels: float = 0.0      # [cpu] negatives nearer than this (px, view 0) are skipped; 0 = spec
    spread_weight: float = 0.0       # weight of the spread-out term (keeps descriptors from collapsing); 0 = spec
    alpha: float = 1.0               # detector preservation weight
    det_preserve_on: str = "logits"  # [code] 2-channel logits; [paper] probabilities
    # --- step (d): detector (§6) ---------------------------------------------------------
    epochs_det: int = 4
    focal_gamma: float = 1.0
    beta: float = 1.0                # repeatability weight
    lambda_keep: float = 0.1         # descriptor preservation weight: [code] 0.1; [paper] 1e-3
    rep_loss: str = "weighted"       # [code] dense weighted symmetric KL; [paper] sum over keypoints
    # --- optimiser ---------------------------------------------------------------------
    lr: float = 1.0e-3
    weight_decay: float = 1.0e-8
    plateau_factor: float = 0.1
    plateau_patience: int = 1
    plateau_threshold: float = 1.0e-4
    # plateau: [paper/code] reduce-on-plateau on the epoch's mean loss (the plateau_* fields);
    # halfway: lr for the first half (rounded up) of a step's epochs, plateau_factor * lr after, whatever the
    # losses do, so runs compared against each other follow the same learning-rate path
    lr_schedule: str = "plateau"
    # --- ablations (§7) ------------------------------------------------------------------
    no_desc_rep: bool = False        # r = Ddis / (1 + rel_rep_eps)
    no_desc_dis: bool = False        # r = 1 / (Drep + rel_rep_eps)
    no_det_rep: bool = False         # beta = 0
    no_affine: bool = False          # (a) target view only; (c) one warped view
    # --- validation ----------------------------------------------------------------------
    validate: bool = True
    validate_start: bool = True      # also score the starting model (round -1)
    val_sets: list[str] = field(default_factory=lambda: ["data/homography/hpatches/*", "data/homography/oxford/*"])
    val_long_side: int = 320
    val_max_keypoints: int = 500
    val_threshold: float = 0.0       # 0: the top-k cap decides, so an untrained model is scored too
    val_nms_radius: int = 4
    best_metric: str = "mma3"

    def as_dict(self) -> dict:
        return asdict(self)

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.as_dict(), sort_keys=False)


def _field_types() -> dict[str, object]:
    return typing.get_type_hints(TrainConfig)


def coerce(key: str, value: object) -> object:
    """Convert a YAML/command-line value to the field's type; SekdError when impossible."""
    kind = _field_types()[key]
    try:
        if kind is bool:
            return _as_bool(value)
        if kind in (int, float):
            if isinstance(value, bool) or (kind is int and isinstance(value, float) and not value.is_integer()):
                raise ValueError
            return kind(float(value)) if kind is int else float(value)
        if kind is str:
            return "" if value is None else str(value)
        if typing.get_origin(kind) is list:
            item = typing.get_args(kind)[0]
            values = value if isinstance(value, (list, tuple)) else [value]
            return [item(v) for v in values]
    except (TypeError, ValueError):
        pass
    raise SekdError(f"config key {key!r}: cannot use {value!r} as {getattr(kind, '__name__', kind)}")


def _as_bool(value: object) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.lower() in ("true", "yes", "on", "1", "false", "no", "off", "0"):
        return value.lower() in ("true", "yes", "on", "1")
    if value in (0, 1):
        return bool(value)
    raise ValueError


def apply(config: TrainConfig, values: dict, source: str) -> TrainConfig:
    """A copy of ``config`` with ``values`` set; unknown keys are a SekdError naming ``source``."""
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise SekdError(f"{source}: unknown config key(s) {', '.join(unknown)}; see docs/training.md for the fields")
    return dataclasses.replace(config, **{k: coerce(k, v) for k, v in values.items()})


def read_yaml(path: Path) -> dict:
    """A YAML mapping from ``path`` (SekdError if missing or not a mapping)."""
    path = Path(path)
    if not path.is_file():
        raise SekdError(f"{path}: config file not found")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise SekdError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from exc
    if not isinstance(data, dict):
        raise SekdError(f"{path}: expected a mapping of config keys to values")
    return data


def parse_set(items: typing.Iterable[str]) -> dict:
    """``["lr=1e-4", "val_sets=[a, b]"]`` -> ``{"lr": "1e-4", "val_sets": ["a", "b"]}`` (values parsed as YAML)."""
    values = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise SekdError(f"--set {item!r}: expected KEY=VALUE")
        try:
            values[key.strip()] = yaml.safe_load(text) if text.strip() else ""
        except yaml.YAMLError:
            values[key.strip()] = text
    return values


def schedule_config(name: str) -> TrainConfig:
    """The named schedule shipped with the package."""
    if name not in SCHEDULES:
        raise SekdError(f"unknown schedule {name!r}; choose one of {', '.join(SCHEDULES)}")
    return apply(TrainConfig(), read_yaml(CONFIG_DIR / f"{name}.yaml"), f"schedule {name}")


def resolve_config(schedule: str | None = None, config_file: Path | None = None,
                   overrides: dict | None = None) -> TrainConfig:
    """Schedule (explicit, else the file's ``schedule`` key, else cpu) -> file -> overrides; validated."""
    file_values = read_yaml(config_file) if config_file else {}
    name = schedule or (overrides or {}).get("schedule") or file_values.get("schedule") or "cpu"
    config = schedule_config(str(name))
    config = apply(config, file_values, str(config_file))
    config = apply(config, dict(overrides or {}), "override")
    config.schedule = str(name)
    validate(config)
    return config


#: Inclusive ranges of numeric fields (None: unbounded on that side); ``_OPEN`` fields must exceed their low end.
RANGES: dict[str, tuple[float | None, float | None]] = {
    "seed": (0, None), "num_threads": (0, 1024), "num_workers": (0, 256),
    "rounds": (1, 1000), "subset_factor": (1, 1000), "random_keypoints": (0, 100_000), "random_score": (0, 1),
    "alpha_round0": (0, None), "long_side": (0, 8192), "size_multiple": (4, 256),
    "crop_height": (16, 4096), "crop_width": (16, 4096), "batch_size": (1, 4096),
    "num_warps": (0, 256), "border_band": (0, 1000), "nms_radius": (0, 100), "max_keypoints": (1, 100_000),
    "det_threshold": (0, 1), "rel_threshold": (0, None), "rel_min_keypoints": (0, None),
    "det_border_factor": (0, None), "rel_border_factor": (0, None), "rel_radius": (1, 100), "rel_stride": (1, 100),
    "rel_rep_eps": (0, None), "rel_dist_eps": (0, None), "rel_count_eps": (0, None), "label_chunk": (1, 4096),
    "epochs_desc": (1, 10_000), "epochs_det": (1, 10_000), "ratio_threshold": (0, None), "margin": (0, None),
    "neg_min_distance": (0, None), "neg_self_penalty": (0, None), "neg_min_pixels": (0, None),
    "spread_weight": (0, None), "alpha": (0, None), "focal_gamma": (0, None), "beta": (0, None),
    "lambda_keep": (0, None), "lr": (0, 10), "weight_decay": (0, None), "plateau_factor": (0, 1),
    "plateau_patience": (0, None), "plateau_threshold": (0, None),
    "val_long_side": (0, 8192), "val_max_keypoints": (1, 100_000), "val_threshold": (0, 1), "val_nms_radius": (0, 100),
}
_OPEN = ("lr", "plateau_factor", "ratio_threshold", "margin", "rel_rep_eps", "rel_count_eps")
#: Ranges [low, high] of the augmentation draws, with the bounds their values must stay within.
RANGE_PAIRS = {"brightness": (0, None), "contrast": (0, None), "saturation": (0, None), "hue": (-0.5, 0.5),
               "rotation_deg": (-180, 180), "shear_deg": (-80, 80), "scale": (0.05, 20), "translation": (-1, 1)}


def validate(config: TrainConfig) -> None:
    """Reject values the training cannot run with, or would run with to no effect (SekdError, one line).

    Types are already right (``coerce``); this checks choices, ranges and the relations
    between fields. What needs the machine (memory) is checked by ``check_memory`` at run start.
    """
    for key, allowed in CHOICES.items():
        if getattr(config, key) not in allowed:
            raise SekdError(f"config key {key!r}: {getattr(config, key)!r} is not one of {', '.join(allowed)}")
    for key, (low, high) in RANGES.items():
        value = getattr(config, key)
        if not math.isfinite(value) or (low is not None and (value < low or (key in _OPEN and value <= low))) \
                or (high is not None and value > high):
            raise SekdError(f"config key {key!r} must be {_describe_range(key, low, high)}, got {value}")
    for key in ("crop_height", "crop_width", "size_multiple"):
        if getattr(config, key) % 4:
            raise SekdError(f"config key {key!r} must be a multiple of 4 (the network's stride)")
    for key, (low, high) in RANGE_PAIRS.items():
        pair = getattr(config, key)
        if len(pair) != 2 or not all(math.isfinite(v) for v in pair) or pair[0] > pair[1]:
            raise SekdError(f"config key {key!r} must be a range [low, high], got {pair}")
        if (low is not None and pair[0] < low) or (high is not None and pair[1] > high):
            raise SekdError(f"config key {key!r} must lie within {_describe_range(key, low, high)}, got {pair}")
    if config.long_side and (config.long_side < config.size_multiple):
        raise SekdError(f"config key 'long_side' ({config.long_side}) must be 0 or >= size_multiple "
                        f"({config.size_multiple})")
    for key in ("crop_height", "crop_width"):
        if config.long_side and getattr(config, key) > config.long_side:
            raise SekdError(f"config key {key!r} ({getattr(config, key)}) must be <= long_side ({config.long_side}): "
                            "training images are resized so their long side is long_side, the rest would be padding")
    if config.num_warps < 1 and not config.no_affine:
        raise SekdError("config key 'num_warps' must be >= 1 (step (c) needs a warped view)")
    if config.round0_random and config.random_keypoints < 1:
        raise SekdError("config key 'random_keypoints' must be >= 1 when round0_random is set")


def _describe_range(key: str, low, high) -> str:
    if low is not None and high is not None:
        return f"in ({low}, {high}]" if key in _OPEN else f"between {low} and {high}"
    return f"> {low}" if key in _OPEN else f">= {low}"


#: Bytes of memory per pixel of one view in a training step: forward + backward of the network
#: (about 3 KB, measured with ``fast_deconv`` on the CPU) plus the frozen reference forward (0.8 KB).
TRAIN_BYTES_PER_PIXEL = 4000
#: Bytes per pixel of one view in a labelling forward (no gradients; measured 0.75-0.8 KB).
LABEL_BYTES_PER_PIXEL = 1000
#: The process itself (torch, the model, cached images): a floor for the estimate.
BASE_BYTES = 600 * 2**20


def step_memory(config: TrainConfig) -> int:
    """Estimated peak bytes of one training step (or one labelling chunk, if larger) in one process."""
    train = 2 * config.batch_size * config.crop_height * config.crop_width * TRAIN_BYTES_PER_PIXEL
    side = config.long_side or 4096  # 0 keeps the images' size: assume a large photo
    label = config.label_chunk * side * side * LABEL_BYTES_PER_PIXEL
    return BASE_BYTES + max(train, label)


def physical_memory() -> int | None:
    """Bytes of RAM of this machine (None where unknown)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def check_memory(config: TrainConfig, available: int | None = None) -> None:
    """SekdError when one step would need more memory than the machine has (``available`` bytes, default its RAM)."""
    available = physical_memory() if available is None else available
    need = step_memory(config)
    if available and need > 0.9 * available:
        raise SekdError(
            f"config: one training step needs about {need / 2**30:.1f} GB (batch_size {config.batch_size} x 2 views "
            f"of {config.crop_height} x {config.crop_width} px, label_chunk {config.label_chunk} views of "
            f"{config.long_side or 'full-size'} px) but this machine has {available / 2**30:.1f} GB; lower "
            "crop_height/crop_width, batch_size, label_chunk or long_side")


def differing_fields(a: TrainConfig, b: TrainConfig, ignore: typing.Iterable[str] = ()) -> list[str]:
    """Names of the fields (in declaration order) whose values differ, except those in ``ignore``."""
    skip = set(ignore)
    return [f.name for f in dataclasses.fields(TrainConfig)
            if f.name not in skip and getattr(a, f.name) != getattr(b, f.name)]


def load_run_config(path: Path) -> TrainConfig:
    """The resolved config saved in a run folder."""
    config = apply(TrainConfig(), read_yaml(path), str(path))
    validate(config)
    return config
