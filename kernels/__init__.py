"""OpenCL C sources of Drape's solvers, shipped as package data (see cloth.cl)."""
