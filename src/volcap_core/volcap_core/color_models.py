"""The names of the per-camera colour model families (``volcap_core.color.ColorModel``), importable
without colour-science: settings offer them as choices."""

METHODS = ('paper_diagonal', 'matrix_3x3', 'affine_3x4', 'root_polynomial_2', 'root_polynomial_3', 'gamma_3x3')
