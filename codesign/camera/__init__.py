"""The differentiable camera: mask -> phase -> PSF -> pixel kernel -> sensor image, and the OTF a restorer needs."""
from codesign.camera.build import build_camera, build_sensor_spec
from codesign.camera.camera import Camera, OpticsOutputs, field_of_view

__all__ = ["Camera", "OpticsOutputs", "build_camera", "build_sensor_spec", "field_of_view"]
