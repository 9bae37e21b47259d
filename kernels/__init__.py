"""OpenCL C sources of Drape's solvers, shipped as package data: the programs cloth.cl (the cloth
solvers; it opens with the list of the files it includes) and encode.cl (the frame's wire bytes)."""
