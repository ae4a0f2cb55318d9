"""Pure array geometry: arrays in, arrays out, no file access, no mvrecon imports outside this package. numpy,
and numba for the inner loops of kernels.py, which load at their first call."""
