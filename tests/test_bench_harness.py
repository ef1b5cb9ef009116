"""The benchmark harnesses time the code they name (bench/ is not a test; its plumbing is)."""
from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _bench_module(name: str):
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module                 # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_fit_cli_runs_the_checkout_it_is_given(tmp_path, monkeypatch):
    """``bench/fit_cli.py --against ROOT`` pairs calls of two checkouts: each call must import
    its own checkout's ``ucad_cl``, also when the bench is started inside the other checkout
    (``python -m`` puts the working folder ahead of ``PYTHONPATH``: it ran this checkout's code
    twice until stop 51)."""
    fit_cli = _bench_module("fit_cli")
    other = tmp_path / "other"
    (other / "ucad_cl").mkdir(parents=True)
    (other / "ucad_cl" / "__init__.py").write_text("")
    (other / "ucad_cl" / "cli.py").write_text(
        "import json, sys\nfrom pathlib import Path\n"
        "a = sys.argv[1:]\nout = Path(a[a.index('--out') + 1]); out.mkdir(parents=True)\n"
        "doc = {'seconds': {'all': 0.0}, 'code': __file__, 'mesh': a[a.index('--mesh') + 1]}\n"
        "(out / (Path(a[1]).stem + '.json')).write_text(json.dumps(doc))\n")
    monkeypatch.chdir(ROOT)                     # started inside this checkout, relative paths
    (tmp_path / "photo.png").write_bytes(b"")
    wall, doc = fit_cli.fit_call(other, tmp_path / "photo.png", ["0", "0", "1", "1"],
                                 tmp_path / "catalog", tmp_path / "out", "abc")
    assert wall > 0
    assert doc["code"] == str(other / "ucad_cl" / "cli.py") and doc["mesh"] == "abc"
    assert json.loads((tmp_path / "out" / "photo.json").read_text())["code"] == doc["code"]


def test_fit_cli_byte_compiles_both_checkouts(tmp_path, monkeypatch):
    """Both sides of a pair start with up-to-date ``.pyc`` files, whatever
    ``PYTHONDONTWRITEBYTECODE`` says: a checkout without them compiles its sources in every
    call (stop 51: a fresh worktree of old code paid that in every call, this checkout for ten
    edited modules)."""
    fit_cli = _bench_module("fit_cli")
    monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")
    source = tmp_path / "ucad_cl" / "sub" / "mod.py"
    source.parent.mkdir(parents=True)
    source.write_text("X = 1\n")
    fit_cli.byte_compiled(tmp_path)
    assert Path(importlib.util.cache_from_source(str(source))).is_file()


def test_fit_bench_splits_answers_by_the_fits_uncertain_flag():
    """``bench/fit.py``'s margin line: the end-to-end answers below ``fit.UNCERTAIN_MARGIN``
    and the rest, each with how many are right; photos without a margin (mesh given, failed)
    are not counted."""
    from ucad_cl.fit import UNCERTAIN_MARGIN

    fit = _bench_module("fit")
    low, high = UNCERTAIN_MARGIN / 2, UNCERTAIN_MARGIN * 3
    rows = [(None, {"end to end": fit.Score(top1=t, margin=m)})
            for t, m in ((0.0, low), (0.0, low), (1.0, low), (1.0, high), (1.0, high),
                         (0.0, high), (1.0, UNCERTAIN_MARGIN), (1.0, float("nan")))]
    rows.append((None, {"mesh given": fit.Score(margin=low)}))
    assert fit.margin_line(rows) == (
        f"retrieval uncertain (margin < {UNCERTAIN_MARGIN:g}): 3 of 7, 1 of them right; "
        "the rest: 3 of 4 right")
