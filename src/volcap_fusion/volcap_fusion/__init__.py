"""TSDF fusion, mesh and point-cloud output, volumetric sequence writer for volcap."""

# Default TSDF voxel edge (metres): the best measured accuracy on the 8-camera studio. Here,
# not in tsdf.py, so the command line can show it without importing Open3D.
VOXEL_SIZE = 0.004
