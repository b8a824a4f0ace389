"""docs/paper.md holds the twin's numbers: its tables are recomputed on the coarse mesh here.

``tools/paper_numbers.py`` computes every value of the generated blocks of
docs/paper.md (on the default mesh, 15 steps per curve, when the docs are written).
Here the same computation runs on the coarse mesh of ``conftest.COARSE`` with 2 steps
per curve, and every value must agree with the docs within the script's
``tolerance`` (coupling indices 0.3 points, forces and capacitance changes 0.5 %,
fields and voltages 1.5 %, 3 % at the peak field, mesh-study values 0.001 points),
and every verdict must come out the same: the docs can neither go stale nor claim a
verdict the numbers do not give.  232 curves on 2 workers, about 75 s.
"""

import importlib.util
import sys
from pathlib import Path

import pytest
from conftest import COARSE

from dea_array_twin import ArrayConfig

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "paper.md"


@pytest.fixture(scope="module")
def paper_numbers():
    spec = importlib.util.spec_from_file_location("paper_numbers", ROOT / "tools" / "paper_numbers.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["paper_numbers"] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_the_docs_tables_are_rendered_from_their_numbers_block(paper_numbers):
    text = DOC.read_text()
    assert paper_numbers.read_blocks(text) == paper_numbers.render(paper_numbers.read_numbers(text))


def test_the_docs_numbers_and_verdicts_hold_on_the_coarse_mesh(paper_numbers):
    docs = paper_numbers.read_numbers(DOC.read_text())
    fresh = paper_numbers.compute(ArrayConfig(**COARSE), steps=2, workers=2, log=lambda text: None)
    assert paper_numbers.mismatches(docs, fresh) == []
    assert paper_numbers.verdicts(fresh) == paper_numbers.verdicts(docs)


def test_a_docs_number_off_by_more_than_its_tolerance_is_reported(paper_numbers):
    docs = paper_numbers.read_numbers(DOC.read_text())
    off = dict(docs, **{"spacing.1mm.eta_f_lv": docs["spacing.1mm.eta_f_lv"] + 0.31,
                        "curves.1.10.fmax.DE2.free.lv_N": docs["curves.1.10.fmax.DE2.free.lv_N"] * 1.006})
    off.pop("spacing.15mm.eta_c")
    messages = paper_numbers.mismatches(docs, off)
    assert [m.split(":")[0] for m in messages] == ["spacing.15mm.eta_c", "curves.1.10.fmax.DE2.free.lv_N",
                                                  "spacing.1mm.eta_f_lv"]
