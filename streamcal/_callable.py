"""Let ``streamcal.fit`` and ``streamcal.diagnose`` be both subpackages and functions (SPEC §5).

Importing a subpackage binds its module object to the parent's attribute of the same name, which
would hide a function of that name; giving the module a ``__call__`` keeps ``streamcal.fit(...)``
working whichever was bound.
"""
from __future__ import annotations

import sys
import types


def make_module_callable(module_name: str, function_name: str) -> None:
    module = sys.modules[module_name]

    class _CallableModule(types.ModuleType):
        def __call__(self, *args, **kwargs):
            return getattr(self, function_name)(*args, **kwargs)

    module.__class__ = _CallableModule
