"""The volcap pipeline: how a camera's frames become cleaned, corrected views
(``camera.CameraPipeline``), how views become a model (``rig``), and the offline replay of a bag
through them (``replay``). Above the stages, below the evaluation and the bringup; no rclpy."""

# `volcap fuse-frames`: a folder of one moving camera (a room from inside, a table top) is not a
# studio rig, so it fuses with its own preset of FusionConfig: 1 cm voxels (rooms are metres
# across), a voxel seen by more than one frame (a moving camera sees each surface many times, and
# a single stray frame would otherwise leave floating surfaces) and depth to the sensor's limit.
FOLDER_FUSION = {'voxel_size': 0.01, 'weight_threshold': 1.0, 'depth_max': 6.5}
