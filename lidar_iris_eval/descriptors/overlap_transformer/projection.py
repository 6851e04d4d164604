"""OverlapNet's range projection, as OverlapTransformer feeds it to its network.

The authors' ``range_projection`` (OverlapNet, reused by OverlapTransformer in
``tools/utils/utils.py``), restated from its definition:

* points with ``0 < r < max_range`` (``r = ||(x, y, z)||``, ``max_range = 80`` m)
  are kept;
* column ``u = floor(W * (1 - atan2(y, x) / pi) / 2)``: column 0 looks backwards
  (azimuth +180 degrees) and the columns run clockwise seen from above, the
  forward direction (azimuth 0) at ``u = W / 2``;
* row ``v = floor(H * (1 - (asin(z / r) - fov_down) / (fov_up - fov_down)))``:
  row 0 at the top of the field of view (+3 degrees), row ``H - 1`` at its
  bottom (-25 degrees);
* both clamped into the image (points above or below the field of view land in
  the first or last row), and the nearest point of a pixel wins;
* empty pixels hold -1.

The authors compute in float32 (their scans are float32), and so does this,
but for the two angles (float64, rounded to float32: see :func:`pixel_coordinates`).

Depth format, and why it matters (OverlapTransformer issue #18): the authors'
``gen_depth_data.py`` writes that float image with ``cv2.imwrite`` to an 8-bit
PNG and their training and test scripts read the PNG back. OpenCV converts the
float depths to 8 bits by rounding to the nearest integer (ties to even) and
saturating to [0, 255], so the network saw **whole metres** and **0** for empty
pixels. Feeding the float image directly (what the C++ demo ``fast_ot.cpp``
does, and what "use .npy" advice in their issues amounts to) gives fractional
depths and -1 for empty pixels: a different input distribution for the same
weights. ``depth_format="png"`` reproduces the PNG round trip (the input the
published weights were trained and evaluated on); ``"float"`` keeps the
in-code float image.
"""

from __future__ import annotations

import numpy as np

DEPTH_FORMATS = ("png", "float")


def pixel_coordinates(points: np.ndarray, height: int = 64, width: int = 900,
                      fov_up: float = 3.0, fov_down: float = -25.0,
                      max_range: float = 80.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rows, cols, depth)`` of the points kept by the projection (float32 arithmetic)."""
    pts = np.asarray(points)[:, :3].astype(np.float32, copy=False)
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    depth = np.sqrt((x * x + y * y) + z * z)  # float32, elementwise: the same bits everywhere
    keep = (depth > 0) & (depth < np.float32(max_range))
    pts, depth = pts[keep], depth[keep]
    up, down = np.float32(fov_up / 180.0 * np.pi), np.float32(fov_down / 180.0 * np.pi)
    fov = abs(down) + abs(up)
    # The two angles are computed in float64 and rounded to float32: the float32 angle
    # correctly rounded but in ~1e-9 of cases. NumPy's own float32 arctan2 and arcsin
    # differ by an ulp between CPUs (SIMD kernels on AVX-512 machines, libm elsewhere),
    # and where a scan's azimuth grid meets the 900 columns (simulated scans: 1.2 % of
    # the points sit on a column edge) that ulp moves points across columns, so figures
    # changed with the machine (tests/test_ot_projection.py).
    p64 = pts.astype(np.float64)
    yaw = (-np.arctan2(p64[:, 1], p64[:, 0])).astype(np.float32)
    ratio = np.clip(p64[:, 2] / depth.astype(np.float64), -1.0, 1.0)
    pitch = np.arcsin(ratio).astype(np.float32)
    u = np.floor(np.float32(0.5) * (yaw / np.float32(np.pi) + np.float32(1.0)) * np.float32(width))
    v = np.floor((np.float32(1.0) - (pitch + abs(down)) / fov) * np.float32(height))
    cols = np.clip(u, 0, width - 1).astype(np.int64)
    rows = np.clip(v, 0, height - 1).astype(np.int64)
    return rows, cols, depth


def range_image(points: np.ndarray, height: int = 64, width: int = 900,
                fov_up: float = 3.0, fov_down: float = -25.0, max_range: float = 80.0,
                depth_format: str = "png") -> np.ndarray:
    """The ``(height, width)`` float32 depth image of ``points`` (module docstring)."""
    if depth_format not in DEPTH_FORMATS:
        raise ValueError(f"depth_format must be one of {DEPTH_FORMATS}, got {depth_format!r}")
    rows, cols, depth = pixel_coordinates(points, height, width, fov_up, fov_down, max_range)
    image = np.full(height * width, np.inf, dtype=np.float32)
    np.minimum.at(image, rows * width + cols, depth)  # the nearest point of each pixel
    image[np.isinf(image)] = -1.0
    image = image.reshape(height, width)
    if depth_format == "png":  # cv2.imwrite(float -> 8 bit) then imread: round, saturate
        image = np.clip(np.rint(image), 0, 255).astype(np.float32)
    return image
