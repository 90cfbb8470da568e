"""COLMAP side: database import, verification, mapping, relative pose, export."""
