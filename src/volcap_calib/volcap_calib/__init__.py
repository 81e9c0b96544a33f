"""ChArUco and colour-chart board; extrinsic and colour calibration for volcap."""
