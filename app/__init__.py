"""smartroom: real-time multi-camera human motion capture over Eclipse Zenoh."""

__version__ = "0.1.0"
