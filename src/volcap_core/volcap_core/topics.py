"""Topic names of the volcap contract (docs/architecture.md). Per-camera names are relative to the
camera namespace ``cam<i>`` so that a launch can remap them onto a vendor driver's topics."""
import yaml

COLOR_IMAGE = 'color/image_raw'
COLOR_INFO = 'color/camera_info'
# image_transport's compressed colour (JPEG from the Azure Kinect driver or Orbbec MJPG)
COLOR_COMPRESSED = 'color/image_raw/compressed'
DEPTH_IMAGE = 'depth/image_raw'
DEPTH_INFO = 'depth/camera_info'
DEPTH_CLEAN = 'depth/image_clean'
DEPTH_CLEAN_INFO = 'depth/image_clean/camera_info'
POINTS = 'points'
COLOR_CORRECTED = 'color/image_corrected'
COLOR_CORRECTED_INFO = 'color/image_corrected/camera_info'

RIG = 'volcap/rig'
PHASE = 'volcap/phase'
CALIBRATE = 'volcap/calibrate'
CALIBRATION = 'volcap/calibration'
CAMERA_POSES = 'volcap/camera_poses'
FUSED_POINTS = 'volcap/points'
MESH = 'volcap/mesh'
MESH_GLB = 'volcap/mesh/glb'
DIAGNOSTICS = 'volcap/diagnostics'
# Which capture frame sets a live graph processes (volcap_core.admission), from volcap live.
ADMISSION = 'volcap/admission'
# The drivers' fixed frames (depth-to-colour extrinsic), as tf2's static broadcaster sends them.
TF_STATIC = 'tf_static'

# Topics whose last message a late subscriber must still get (transient-local).
LATCHED = (RIG, CALIBRATION, CAMERA_POSES, ADMISSION)

# Session phases announced on PHASE (std_msgs/String YAML) at the first stamp of each part.
CLEAN_PLATE, CALIBRATION_PHASE, CAPTURE = 'clean_plate', 'calibration', 'capture'
PHASES = (CLEAN_PLATE, CALIBRATION_PHASE, CAPTURE)


def camera_topic(camera: str, topic: str) -> str:
    return f'{camera}/{topic}'


def camera_names(count: int) -> list[str]:
    return [f'cam{i}' for i in range(count)]


def parse_phase(text: str) -> str | None:
    """The phase a ``volcap/phase`` message (YAML ``{phase: ..., frames: N, since_ns: S}``)
    announces; None when the text is not such a message."""
    return parse_phase_change(text)[0]


def parse_phase_change(text: str) -> tuple[str | None, int | None]:
    """(phase, since_ns) of a ``volcap/phase`` message: ``since_ns``, when the message carries
    it, is the capture stamp from which frames belong to the phase (a node that sees the frames
    late, after processing elsewhere, still places the change exactly); None without it."""
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError:
        return None, None
    if not isinstance(doc, dict) or not isinstance(doc.get('phase'), str):
        return None, None
    since = doc.get('since_ns')
    return doc['phase'], since if isinstance(since, int) and not isinstance(since, bool) else None
