"""Marker-based motion capture (thesis §6.4, §6.6): the generalised symmetric epipolar
distance (:mod:`.epipolar`), the marker likelihood (:mod:`.likelihood`), the annealed
particle filter on it (:mod:`.tracking`) and synthetic detections for sweeps
(:mod:`.synthetic`). No bus here; the pose worker's marker mode is still to come."""
