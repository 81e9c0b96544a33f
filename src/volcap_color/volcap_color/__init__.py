"""Per-camera colour correction, neural harmonisation and colour evaluation for volcap."""
