"""Generated C for the sampler: the SX-to-C lane emitter, the cached and verified libraries,
vector maths, the in-kernel random number generator and the diagnostics kernels."""

from workbench.sampling.kernels.library import get_threads, sampler_library, set_threads

__all__ = ["get_threads", "sampler_library", "set_threads"]
