"""Feature detection and description (SIFT via OpenCV, keypoints in COLMAP's pixel convention)."""
