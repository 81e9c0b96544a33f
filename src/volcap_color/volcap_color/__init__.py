"""Per-camera colour correction (the color_corrector node), chart-free and neural harmonisation."""
