"""QoS profiles: drivers publish reliable (REP 2003), consumers of camera streams subscribe
reliable keep-last (``CAMERA``, measured below), rig-level state is transient-local so late
joiners get the last message."""
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# Camera drivers: reliable, shallow history so a slow reader never holds many 2.7 MB frames.
DRIVER = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
# Consumers that may lose frames (monitors, benchmarks): best effort, matches any publisher.
SENSOR = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=4, reliability=ReliabilityPolicy.BEST_EFFORT,
                    durability=DurabilityPolicy.VOLATILE)
# Consumers of camera streams on a rig (the default): reliable, keep-last. Measured by
# bench/rig_transport.py (8 cameras, 30 fps, 24 streams): from a stock Fast DDS driver best
# effort got 10-18 % of the frames and reliable 36-42 % (a lost fragment loses a best-effort
# frame); from a driver with the volcap profile both got 100 %. Against the drivers' KEEP_LAST
# writers a reliable reader never holds the writer back, so no backlog builds.
CAMERA = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=2, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
# Consumers that must not lose a frame (the calibration service's board views): reliable, so a
# frame published while discovery is still settling is resent rather than lost. A KEEP_LAST
# driver writer overwrites unacknowledged frames instead of blocking on a slow reader.
EVERY_FRAME = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=4, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
# Rig description, calibration, camera poses.
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
# /tf_static as tf2's StaticTransformBroadcaster offers it (each driver's last message kept).
TF_STATIC = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)
# Diagnostics and small events.
EVENTS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
