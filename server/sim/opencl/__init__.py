"""OpenCL back end of the simulation: device choice and program cache, the merged CL world."""
