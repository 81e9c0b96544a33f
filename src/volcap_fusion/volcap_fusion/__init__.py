"""TSDF fusion, mesh and point-cloud output, volumetric sequence writer for volcap."""
