"""thermod: gyro-aided real-time deblurring for microbolometer thermal cameras."""

__version__ = "0.1.0"
