"""QoS profiles: drivers publish reliable (REP 2003), consumers subscribe with sensor-data QoS,
rig-level state is transient-local so late joiners get the last message."""
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# Camera drivers: reliable, shallow history so a slow reader never holds many 2.7 MB frames.
DRIVER = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
# Consumers of camera streams: best effort, matches reliable and best-effort publishers.
SENSOR = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=4, reliability=ReliabilityPolicy.BEST_EFFORT,
                    durability=DurabilityPolicy.VOLATILE)
# Consumers that must not lose a frame (the calibration service's board views): reliable, so a
# frame published while discovery is still settling is resent rather than lost. A KEEP_LAST
# driver writer overwrites unacknowledged frames instead of blocking on a slow reader.
EVERY_FRAME = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=4, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
# Rig description, calibration, camera poses.
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
# Diagnostics and small events.
EVENTS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
