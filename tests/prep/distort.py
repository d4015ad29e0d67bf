"""Distorted pictures for the opencv tests: what a pinhole camera with OpenCV's radial and tangential
distortion would have recorded of a scene rendered through an ideal pinhole."""
import cv2
import numpy as np


def distort(rgb: np.ndarray, camera, coefficients) -> np.ndarray:
    """rgb (H, W, 3) seen by the ideal pinhole `camera` (pixel centres at +0.5) -> the picture of the same
    camera with OpenCV distortion (k1, k2, p1, p2): each distorted pixel samples the ideal picture where
    its ray lands (bilinear)."""
    k = np.array([[camera.fx, 0, camera.cx - 0.5], [0, camera.fy, camera.cy - 0.5], [0, 0, 1]])
    h, w = rgb.shape[:2]
    grid = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 1, 2).astype(np.float64)
    ideal = cv2.undistortPoints(grid, k, np.asarray(coefficients, np.float64), P=k).reshape(h, w, 2)
    return cv2.remap(rgb, ideal[..., 0].astype(np.float32), ideal[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
