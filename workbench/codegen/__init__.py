"""CasADi Functions to cached, verified shared libraries (DESIGN "Code generation")."""

from workbench.codegen.cache import CompileError, Library, build_counts, build_library, cache_dir
from workbench.codegen.toolchain import Toolchain, find_toolchain

__all__ = ["CompileError", "Library", "Toolchain", "build_counts", "build_library", "cache_dir",
           "find_toolchain"]
