"""Load a script of benchmarks/ as a module (they import their sibling ``provenance``)."""

import contextlib
import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


@contextlib.contextmanager
def benchmark_module(name: str):
    """``benchmarks/<name>.py`` imported, with ``benchmarks/`` on the path while it is in use."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    module_name = f"{name}_benchmark"
    try:
        spec = importlib.util.spec_from_file_location(module_name, ROOT / "benchmarks" / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[module_name] = module  # dataclasses look their module up
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(module_name, None)
        sys.path.remove(str(ROOT / "benchmarks"))
