"""Articulated body pose of every tracked person from the voxels (thesis Ch. 6-7):
body model, fleshed model and likelihood, APF / SHBM-APF / DDM-APF, detection-driven
(re)initialisation (Fontmarty's IAPF)."""
