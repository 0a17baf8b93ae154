"""Array aliases for annotations: the dtype a function takes or returns.

numpy's types carry the dtype only; shapes, units and frames stay in each docstring.
"""

from __future__ import annotations

from typing import TypeAlias

import numpy as np
from numpy.typing import NDArray

FloatArray: TypeAlias = NDArray[np.float64]
"""Points, poses, residuals: float64 throughout the solvers."""

Float32Array: TypeAlias = NDArray[np.float32]
"""Depth images (metres) and pixel positions as OpenCV returns them."""

BoolArray: TypeAlias = NDArray[np.bool_]
"""Masks: valid pixels, inliers, occupied cells."""

IndexArray: TypeAlias = NDArray[np.intp]
"""Indices into another array (np.nonzero, np.argsort, np.flatnonzero)."""

Int64Array: TypeAlias = NDArray[np.int64]
"""Integer cell or pixel coordinates."""

GreyImage: TypeAlias = NDArray[np.uint8]
"""(H, W) 8-bit intensity images; (H, W, 3) RGB colour images share the dtype."""

RealArray: TypeAlias = NDArray[np.floating]
"""Inputs taken at either float precision, e.g. depth as float32 from a sensor or float64."""
