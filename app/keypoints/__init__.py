"""Learned 2D body keypoints: the detector (optional extra) and their fusion into the pose filters."""
