"""benchmarks.forward_programs compare: the ledger entries come only from tasks whose
every forward digest is equal and whose fingerprint changed (hand-made records)."""

import json

from benchmarks import forward_programs as fp


def _doc(**tasks):
    return {"tasks": {name: {"fingerprint": f, "spec_digest": s,
                             "batches": {"1": {"step": step, "values": "v"},
                                         "4": {"step": step, "values": "w"}}}
                      for name, (f, s, step) in tasks.items()}}


def test_compare_names_equal_programs_and_differing_digests(tmp_path, capsys):
    old = _doc(a=("fa0", "sa", "x"), b=("fb0", "sb", "y"), c=("fc", "sc", "z"),
               d=("fd0", "sd", "u"))
    new = _doc(a=("fa1", "sa", "x"), b=("fb1", "sb", "Y"), c=("fc", "sc", "z"),
               d=("fd1", "sD", "u"))
    same, differ = fp.compare(old, new)
    assert same == [("a", "fa0", "fa1"), ("c", "fc", "fc")]
    assert differ == [("b", ["1/step", "4/step"]), ("d", ["spec_digest"])]
    paths = []
    for name, doc in (("old", old), ("new", new)):
        paths.append(tmp_path / f"{name}.json")
        paths[-1].write_text(json.dumps(doc))
    assert fp.main(["compare", *map(str, paths), "--evidence", "E"]) == 1
    out = capsys.readouterr()
    assert out.out == "    Equivalence('a', 'fa0', 'fa1', 'E'),\n"  # c: same fingerprint
    assert "b: forward programs differ (1/step, 4/step)" in out.err


def test_compare_values_needs_equal_values_and_gradient_values(tmp_path, capsys):
    """``--values``: programs may differ; the values and gradient values must be present
    and equal; the entries printed cover the gradients."""
    old = _doc(a=("fa0", "sa", "x"), b=("fb0", "sb", "y"), c=("fc0", "sc", "z"))
    new = _doc(a=("fa1", "sa", "X"), b=("fb1", "sb", "Y"), c=("fc1", "sc", "Z"))
    for doc, grads in ((old, {"a": "g", "b": "h", "c": "k"}),
                       (new, {"a": "g", "b": "H", "c": None})):
        for name, g in grads.items():
            if g is not None:
                for batch in doc["tasks"][name]["batches"].values():
                    batch["gradient_values"] = g
    same, differ = fp.compare(old, new, values=True)
    assert same == [("a", "fa0", "fa1")]
    assert differ == [("b", ["1/gradient_values", "4/gradient_values"]),
                      ("c", ["1/gradient_values", "4/gradient_values"])]
    assert fp.compare(old, new)[0] == []  # the programs differ
    paths = []
    for name, doc in (("old", old), ("new", new)):
        paths.append(tmp_path / f"{name}.json")
        paths[-1].write_text(json.dumps(doc))
    assert fp.main(["compare", "--values", *map(str, paths), "--evidence", "E"]) == 1
    out = capsys.readouterr()
    assert out.out == "    Equivalence('a', 'fa0', 'fa1', 'E', gradients=True),\n"
    assert "b: values differ" in out.err
