"""The one compiled part of streamcal: the robust LM's per-sample loops
(streamcal/fitting/_lmcore.c, see streamcal/fitting/lm_compiled.py). Everything else is in
pyproject.toml. The extension is optional: without a C compiler (GCC or Clang) and the Python
headers the install still succeeds and the numpy engine runs (same results to rounding)."""
import hashlib
from pathlib import Path

from setuptools import Extension, setup

SOURCE = "streamcal/fitting/_lmcore.c"
# compiled in, so a test can tell a build that is older than its source
SOURCE_SHA256 = hashlib.sha256(Path(__file__).with_name("streamcal").joinpath(
    "fitting", "_lmcore.c").read_bytes()).hexdigest()

# -ffp-contract=off: no fused multiply-adds (aarch64 compilers fuse a*b + c by default), so the
# loops round as numpy does on every platform
setup(ext_modules=[Extension("streamcal.fitting._lmcore", [SOURCE],
                             define_macros=[("LMCORE_SOURCE_SHA256", f'"{SOURCE_SHA256}"')],
                             extra_compile_args=["-ffp-contract=off"], optional=True)])
