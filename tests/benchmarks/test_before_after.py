"""benchmarks.before_after: each arm runs its own commit's code, in the asked order, and
every record carries its arm's tags."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from benchmarks import before_after

BENCH = '''import json
from probe import VALUE
print("compiling...")
print(json.dumps({"value": VALUE}))
'''


def _git(repo, *args):
    subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True)


@pytest.fixture
def repo(tmp_path):
    """A repository whose two commits' package module ``probe`` says 1, then 2."""
    repo = tmp_path / "repo"
    src = repo / "packages" / "probe" / "src"
    src.mkdir(parents=True)
    (repo / "bench.py").write_text(BENCH)
    _git(repo, "init", "-q")
    for value in (1, 2):
        (src / "probe.py").write_text(f"VALUE = {value}\n")
        _git(repo, "add", "-A")
        _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", f"v{value}")
    return repo


def test_abba_runs_each_commit_s_code_in_order_and_tags_its_records(repo, tmp_path):
    out = tmp_path / "out.jsonl"
    rc = before_after.main(["--repo", str(repo), "--before", "HEAD~1", "--after", "HEAD",
                            "--cmd", "python bench.py", "--out", str(out)])
    assert rc == 0
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    assert [(r["arm"], r["code"], r["value"]) for r in recs] == [
        (1, "before", 1), (2, "after", 2), (3, "after", 2), (4, "before", 1)]
    head = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], text=True,
                          capture_output=True).stdout.strip()
    assert {r["commit"] for r in recs if r["code"] == "after"} == {head[:12]}
    assert all(r["load1_at_arm_start"] >= 0 for r in recs)
    # the worktrees are gone
    listed = subprocess.run(["git", "-C", str(repo), "worktree", "list"], text=True,
                            capture_output=True).stdout.strip().splitlines()
    assert len(listed) == 1


def test_an_existing_out_file_or_an_unknown_commit_is_refused(repo, tmp_path, capsys):
    out = tmp_path / "out.jsonl"
    out.write_text("")
    with pytest.raises(SystemExit):
        before_after.main(["--repo", str(repo), "--before", "HEAD~1", "--after", "HEAD",
                           "--cmd", "python bench.py", "--out", str(out)])
    assert "exists" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        before_after.main(["--repo", str(repo), "--before", "nosuchref", "--after", "HEAD",
                           "--cmd", "python bench.py", "--out", str(tmp_path / "o.jsonl")])
    assert "nosuchref" in capsys.readouterr().err


def test_a_failing_command_stops_the_run_and_keeps_what_it_wrote(repo, tmp_path):
    out = tmp_path / "out.jsonl"
    rc = before_after.main(["--repo", str(repo), "--before", "HEAD~1", "--after", "HEAD",
                            "--cmd", "python bench.py", "--cmd", "python -c 'raise SystemExit(3)'",
                            "--out", str(out)])
    assert rc == 1
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    assert [(r["arm"], r["value"]) for r in recs] == [(1, 1)]


def test_sigterm_stops_the_command_and_removes_the_worktrees(repo, tmp_path):
    out, started = tmp_path / "out.jsonl", tmp_path / "started"
    code = f"open({str(started)!r}, 'w'); import time; time.sleep(60)"
    slow = f'python -c "{code}"'
    root = Path(before_after.__file__).resolve().parents[1]
    proc = subprocess.Popen([sys.executable, "-m", "benchmarks.before_after", "--repo",
                             str(repo), "--before", "HEAD~1", "--after", "HEAD", "--cmd",
                             "python bench.py", "--cmd", slow, "--out", str(out)],
                            cwd=root, env={**os.environ, "PYTHONPATH": str(root)})
    deadline = time.monotonic() + 60
    while not started.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert started.exists(), "the slow command never started"
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=30) != 0
    listed = subprocess.run(["git", "-C", str(repo), "worktree", "list"], text=True,
                            capture_output=True).stdout.strip().splitlines()
    assert len(listed) == 1, listed
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    assert [(r["arm"], r["value"]) for r in recs] == [(1, 1)]
