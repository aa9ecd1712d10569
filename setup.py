"""The one compiled part of streamcal: the robust LM's per-sample loops
(streamcal/fitting/_lmcore.c, see streamcal/fitting/lm_compiled.py). Everything else is in
pyproject.toml. The extension is optional: without a C compiler the install still succeeds and
the numpy engine runs (same results to rounding)."""
from setuptools import Extension, setup

setup(ext_modules=[Extension("streamcal.fitting._lmcore", ["streamcal/fitting/_lmcore.c"],
                             optional=True)])
