"""Drape server: fabric cooking, OpenCL solvers, the tick loop and the Zenoh endpoints."""
