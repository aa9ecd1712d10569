"""The one compiled part of streamcal: the robust LM's per-sample loops
(streamcal/fitting/_lmcore.c, see streamcal/fitting/lm_compiled.py). Everything else is in
pyproject.toml. The extension is optional: without a C compiler (GCC or Clang) and the Python
headers the install still succeeds and the numpy engine runs (same results to rounding)."""
from setuptools import Extension, setup

# -ffp-contract=off: no fused multiply-adds (aarch64 compilers fuse a*b + c by default), so the
# loops round as numpy does on every platform
setup(ext_modules=[Extension("streamcal.fitting._lmcore", ["streamcal/fitting/_lmcore.c"],
                             extra_compile_args=["-ffp-contract=off"], optional=True)])
