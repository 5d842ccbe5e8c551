"""Run every benchmark in bench/ (each module ``bench_*.py`` with a ``main()``) and report which failed.

Arguments name the benchmarks to run (a part of the module name); options (``--quick``) are passed on to the
benchmarks that list them in their ``OPTIONS``.
"""

import importlib
import pkgutil
import sys
import traceback

import bench


def main(argv=None):
    args = sys.argv[1:] if argv is None else argv
    options = [a for a in args if a.startswith("--")]
    names = [a for a in args if not a.startswith("--")]
    modules = sorted(m.name for m in pkgutil.iter_modules(bench.__path__) if m.name.startswith("bench_"))
    if names:
        modules = [m for m in modules if any(n in m for n in names)]
    failed = []
    for name in modules:
        print(f"== {name}", flush=True)
        try:
            module = importlib.import_module(f"bench.{name}")
            result = module.main([o for o in options if o in getattr(module, "OPTIONS", ())])
            if result:
                failed.append(name)
        except Exception:
            traceback.print_exc()
            failed.append(name)
    print(f"benchmarks: {len(modules) - len(failed)} ran, {len(failed)} failed {failed if failed else ''}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
