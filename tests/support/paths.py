"""Where things are: this checkout, and the shared data folder beside it."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]  # tests/support/paths.py -> the checkout
SHARED_DATA = REPO.parent / "shared" / "data"  # the real RGB-D sequences, beside the checkout
