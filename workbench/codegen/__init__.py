"""CasADi Functions to cached, verified shared libraries.

The code cache is private to its user and nothing in it is loaded before its identity is
established; :mod:`workbench.codegen.cache` describes the trust model.
"""

from workbench.codegen.cache import CompileError, Library, build_counts, build_library, cache_dir
from workbench.codegen.fpmode import FloatingPointModeError
from workbench.codegen.toolchain import Toolchain, find_toolchain

__all__ = ["CompileError", "FloatingPointModeError", "Library", "Toolchain", "build_counts",
           "build_library", "cache_dir", "find_toolchain"]
