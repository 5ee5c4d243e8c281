"""Write the API reference (HTML, from the docstrings, by pdoc) into docs/api/.

    python scripts/make_api_docs.py [OUT_DIR]

Every module of the library is documented (the command line, ``cblrs.cli``, is documented by
``cblrs --help``). A warning from pdoc (an unresolvable reference, a module that does not
import) fails the build; ``tests/test_api_docs.py`` builds it in a temporary folder.
"""

from __future__ import annotations

import pkgutil
import sys
import warnings
from pathlib import Path

import pdoc

import cblrs

ROOT = Path(__file__).resolve().parents[1]
# Optional extras that are not part of the dev install: their adapters are left out.
SKIPPED = {"cblrs.detectors.ultralytics_yolo"}


def library_modules() -> list[str]:
    """cblrs and every submodule outside ``cblrs.cli``, sorted."""
    names = ["cblrs"] + [
        module.name for module in pkgutil.walk_packages(cblrs.__path__, "cblrs.")
        if not module.name.startswith("cblrs.cli") and module.name not in SKIPPED
    ]
    return sorted(names)


def build(out: Path) -> list[str]:
    """Render the reference into ``out``; the warnings pdoc gave (empty: a clean build)."""
    pdoc.render.configure(docformat="google", footer_text=f"cblrs {cblrs.__version__}",
                          search=False, show_source=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pdoc.pdoc(*library_modules(), output_directory=out)
    # Passing a package and its submodules both is how every module gets a page (a package
    # with an __all__ lists only those names); pdoc notes the repeats, which are harmless.
    # ResourceWarnings are not pdoc's: the garbage collector reports, during the build, a file
    # some earlier code in this process left open (e.g. a test's subprocess pipe).
    return [str(warning.message) for warning in caught
            if "has already been added" not in str(warning.message)
            and not issubclass(warning.category, ResourceWarning)]


def main() -> int:
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "docs" / "api"
    problems = build(out)
    for problem in problems:
        print(f"pdoc: {problem}", file=sys.stderr)
    pages = len(list(out.rglob("*.html")))
    print(f"{pages} pages in {out}" + (f", {len(problems)} warnings" if problems else ""))
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
