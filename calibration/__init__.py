"""Camera model and the contract's calibration file."""
from calibration.camera import Camera
from calibration.loader import Calibration, CalibrationError, load_calibration, parse_calibration, save_calibration

__all__ = ["Camera", "Calibration", "CalibrationError", "load_calibration", "parse_calibration", "save_calibration"]
