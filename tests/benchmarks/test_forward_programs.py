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
