"""Camera model (pinhole + OpenCV distortion, depth scale, world extrinsics) and its calibration."""

from normpos_grasp.camera.model import Camera, RGBDFrame

__all__ = ["Camera", "RGBDFrame"]
