"""labelaudit: audit 3D LiDAR box labels with the generative label-uncertainty model of
"Labels Are Not Perfect: Inferring Spatial Uncertainty in Object Detection" (Feng, Wang et al.)."""

__version__ = "0.1.0"
SCHEMA_VERSION = "1"
