"""The simulation core: cloth parameters, fabric cooking, the float64 reference, Worlds and
quality presets. numpy and OpenCL only: no Zenoh, no threads."""
