"""The volcap pipeline: how a camera's frames become cleaned, corrected views
(``camera.CameraPipeline``), how views become a model (``rig``), and the offline replay of a bag
through them (``replay``). Above the stages, below the evaluation and the bringup; no rclpy."""
