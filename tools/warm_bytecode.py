"""Writes the bytecode cache of every module a rigctl command imports.

Run once by tools/install_venv.sh after the install, with PYTHONDONTWRITEBYTECODE
removed from the environment. A shell that sets that variable (this machine's does) keeps
Python from writing a cache on first use, and every `rigctl` call then compiles what it
imports again: 2.4 s of a 9 s `rigctl solve` here. Importing every rigctl module, and the
plotting modules the procedures import only when they draw, writes the cache once; a
later process reads it whatever its environment says.

A module whose optional dependency is not installed (the service without its extra) is
skipped: the install stays valid, and nothing imports it.
"""

from __future__ import annotations

import importlib
import os
import pkgutil
import sys

# Imported inside the functions that draw, so not reached by importing rigctl's modules.
LAZY_IMPORTS = ("matplotlib.pyplot", "mpl_toolkits.mplot3d", "matplotlib.backends.backend_agg")


def main() -> int:
    if os.environ.get("PYTHONDONTWRITEBYTECODE"):
        message = "warm_bytecode: PYTHONDONTWRITEBYTECODE is set: nothing would be written"
        print(message, file=sys.stderr)
        return 1
    os.environ.setdefault("MPLBACKEND", "Agg")
    import rigctl

    names = [m.name for m in pkgutil.walk_packages(rigctl.__path__, "rigctl.")]
    skipped = []
    for name in [*names, *LAZY_IMPORTS]:
        try:
            importlib.import_module(name)
        except ImportError as error:  # an extra that is not installed
            skipped.append(f"{name} ({error.name or error})")
        except Exception as error:  # a cache is an optimisation: never fail an install
            skipped.append(f"{name} ({type(error).__name__}: {error})")
    if skipped and "-v" in sys.argv:
        print("warm_bytecode: skipped " + ", ".join(skipped), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
