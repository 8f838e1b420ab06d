"""Clear the outputs of notebooks in place, as they must be committed:

    .venv/bin/python notebooks/clear_outputs.py notebooks/*.ipynb

Removes every code cell's outputs, execution count and execution-timing metadata; leaves
sources and everything else as they are. (tests/project/test_notebooks.py fails on a committed
notebook with outputs; ``make test`` executes the notebooks through nbmake without writing
them back.)
"""
from __future__ import annotations

import sys
from pathlib import Path

import nbformat


def clear_outputs(path: str | Path) -> bool:
    """Clear ``path``'s outputs; True if anything was removed (the file is rewritten only then)."""
    path = Path(path)
    nb = nbformat.read(path, as_version=4)
    changed = False
    for cell in nb.cells:
        if cell.cell_type != "code":
            continue
        if cell.outputs or cell.execution_count is not None or "execution" in cell.metadata:
            cell.outputs, cell.execution_count = [], None
            cell.metadata.pop("execution", None)
            changed = True
    if changed:
        tmp = path.with_name(path.name + ".tmp")
        nbformat.write(nb, tmp)
        tmp.replace(path)
    return changed


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__.strip(), file=sys.stderr)
        return 2
    for p in argv:
        print(f"{p}: {'cleared' if clear_outputs(p) else 'already clean'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
