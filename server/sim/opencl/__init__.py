"""OpenCL back end of the simulation: device choice and program cache, the merged CL world."""

__all__: list[str] = []  # import from the modules: device, clworld... (opencl is imported only when asked for)
