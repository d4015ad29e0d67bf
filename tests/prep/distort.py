"""Distorted pictures for the opencv tests: what a pinhole camera with OpenCV's radial and tangential
distortion would have recorded of a scene rendered through an ideal pinhole."""
import cv2
import numpy as np


def distortion_map(camera, coefficients) -> tuple[np.ndarray, np.ndarray]:
    """(map_x, map_y), (H, W) float32 each: where in the ideal picture of the pinhole `camera` (pixel centres
    at +0.5) each pixel of the picture through OpenCV distortion (k1, k2, p1, p2) looks."""
    k = np.array([[camera.fx, 0, camera.cx - 0.5], [0, camera.fy, camera.cy - 0.5], [0, 0, 1]])
    w, h = camera.width, camera.height
    grid = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 1, 2).astype(np.float64)
    ideal = cv2.undistortPoints(grid, k, np.asarray(coefficients, np.float64), P=k).reshape(h, w, 2)
    return ideal[..., 0].astype(np.float32), ideal[..., 1].astype(np.float32)


def distort(rgb: np.ndarray, maps) -> np.ndarray:
    """rgb (H, W, 3), an ideal picture -> the distorted one (bilinear), with maps from distortion_map."""
    return cv2.remap(rgb, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
