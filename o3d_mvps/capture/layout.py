"""Names and defaults of the capture folder format (the layout is drawn in ``o3d_mvps.capture``)."""

from ..model.sensor import DEPTH_RANGE_M  # noqa: F401  (plausible median depth, m: re-exported here)

COLOR_DIR, DEPTH_DIR, MASK_DIR, GROUNDTRUTH_DIR = "color", "depth", "mask", "groundtruth"
INTRINSIC_JSON, DEPTH_INTRINSIC_JSON, CAPTURE_JSON = "intrinsic.json", "depth_intrinsic.json", "capture.json"
COLOR_ENCODINGS = ("srgb", "linear")
#: Colour frame suffixes read (.jpg: Open3D's reconstruction system writes those).
COLOR_SUFFIXES = (".png", ".jpg", ".jpeg")
#: Ground-truth arrays, each groundtruth/<name>.npy, besides groundtruth/light.json.
GT_ARRAYS = ("depth", "normals", "albedo", "poses", "mesh_to_reference")
#: capture.json's "light": the LED on the camera, room light, or a lamp moved by hand around a
#: static camera (the solver's "led", "room" and "point" models).
CAPTURE_LIGHTS = ("led", "room", "point")
#: capture.json's "camera": fixed on a tripod while a light moves (the static-camera, moving-light
#: setting of Peng et al. 2017: no registration, identity poses) or moved around the object.
CAPTURE_CAMERAS = ("static", "moving")
DEFAULT_SETTINGS = {"depth_scale": 1000.0, "depth_trunc": 3.0, "color_encoding": "srgb", "sensor": "unknown"}
