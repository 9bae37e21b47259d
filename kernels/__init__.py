"""OpenCL C sources of Drape's solvers, shipped as package data: the programs cloth.cl (the cloth
solvers; it lists the files it includes, each of which opens with what it does) and encode.cl (the
frame's wire bytes). drape.server.sim.opencl.device puts a program's files together and builds it."""
