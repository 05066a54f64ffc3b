"""scripts/fuzz-coverage's runs: the long stage's fast build whose corpus is
replayed through the checked (ASan + UBSan) build, targets in parallel.

The replay's logic is shown with two stand-in fuzzers (shell scripts printing
what libFuzzer prints): a finding of the replay is the run's finding. The
real thing runs once where clang is installed: can_frame from its fast build
beside a Python target, its corpus replayed.
"""

import json
import shutil
import stat
import sys
import threading
import time

import pytest
import requires

from rt_loop.tools import fuzz_coverage as fc


def _fake_fuzzer(path, text, status):
    path.write_text("#!/bin/sh\necho \"$@\" >> \"$0.args\"\ncat <<'EOF'\n" + text + "\nEOF\nexit " + str(status) + "\n")
    path.chmod(path.stat().st_mode | stat.S_IEXEC)
    return path


@pytest.fixture
def sandbox(tmp_path, monkeypatch):
    monkeypatch.setattr(fc, "BUILD", tmp_path / "build")
    monkeypatch.setattr(fc, "CRASHES", tmp_path / "crashes")
    monkeypatch.setattr(fc, "ROOT", tmp_path)
    return tmp_path


FAST_OK = ("#2\tINITED cov: 10 ft: 20 corp: 2/10b exec/s: 0 rss: 30Mb\n"
           "#5000\tDONE   cov: 12 ft: 25 corp: 3/12b lim: 4 exec/s: 5000 rss: 30Mb\n"
           "Done 5000 runs in 1 second(s)\nstat::number_of_executed_units: 5000")


def test_a_replay_finding_is_the_runs_finding(sandbox, capsys):
    fast = _fake_fuzzer(sandbox / "fast", FAST_OK, 0)
    checked = _fake_fuzzer(sandbox / "checked", (
        "#7\tINITED cov: 11 ft: 21 corp: 3/12b exec/s: 0 rss: 40Mb\n"
        "==42==ERROR: AddressSanitizer: heap-buffer-overflow on address 0x1\n"
        f"Test unit written to {sandbox}/crashes/can_frame/crash-abc\n"
        "SUMMARY: AddressSanitizer: heap-buffer-overflow can_table.c:10 in put_bits"), 1)
    res = fc.run_target("can_frame", fast, None, 5000, checked=checked)
    assert res["executions"] == 5000 and res["kind"] == "C (libFuzzer, fast build)"
    assert res["replay"]["executions"] == 7 and res["replay"]["crashed"]
    assert res["crashed"]
    assert any("heap-buffer-overflow" in f for f in res["findings"])
    assert res["inputs"] == [f"{sandbox}/crashes/can_frame/crash-abc"]
    fast_args = (sandbox / "fast.args").read_text().split()
    replay_args = (sandbox / "checked.args").read_text().split()
    assert "-runs=5000" in fast_args
    # the replay: every input once from the same folders, nothing mutated, no time limit
    assert "-runs=0" in replay_args and not any(a.startswith("-max_total_time") for a in replay_args)
    assert replay_args[-2:] == fast_args[-2:] or replay_args[-1] == fast_args[-1]
    out = capsys.readouterr().out
    assert "replay (checked)" in out and "CRASH" in out


def test_a_clean_replay_keeps_the_run_clean(sandbox):
    fast = _fake_fuzzer(sandbox / "fast", FAST_OK, 0)
    checked = _fake_fuzzer(sandbox / "checked", (
        "#7\tINITED cov: 11 ft: 21 corp: 3/12b exec/s: 0 rss: 40Mb\n"
        "#7\tDONE   cov: 11 ft: 21 corp: 3/12b lim: 4 exec/s: 0 rss: 40Mb\nDone 7 runs in 0 second(s)"), 0)
    res = fc.run_target("can_frame", fast, 10, None, checked=checked)
    assert not res["crashed"] and res["findings"] == [] and res["replay"]["executions"] == 7


def test_a_fast_run_that_found_something_is_not_replayed(sandbox):
    fast = _fake_fuzzer(sandbox / "fast", "runtime error: shift exponent 70 is too large\n"
                        "SUMMARY: UndefinedBehaviorSanitizer: undefined-behavior a.c:1", 1)
    checked = _fake_fuzzer(sandbox / "checked", FAST_OK, 0)
    res = fc.run_target("can_frame", fast, 10, None, checked=checked)
    assert res["crashed"] and "replay" not in res and not (sandbox / "checked.args").exists()


@pytest.mark.parametrize("opt", ["--parallel", "--workers"])
def test_bad_parallel_or_workers_is_one_line(opt, capsys):
    assert fc.main(["can_frame", opt, "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and opt in err


@pytest.mark.skipif(not any(shutil.which(c) for c in ("clang", "clang-14", "clang-15", "clang-16")),
                    reason="clang missing (scripts/fuzz-coverage installs it)")
def test_fast_build_runs_and_its_corpus_is_replayed_checked(tmp_path, capsys, monkeypatch):
    requires.module("atheris")
    monkeypatch.setattr(fc, "GROWN", tmp_path / "grown")
    out = tmp_path / "fc.json"
    assert fc.main(["can_frame", "control_request", "--fast", "--seconds", "3", "--parallel", "2",
                    "--workers", "2", "--keep", "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["build"].startswith("fast") and report["parallel"] == 2
    c, py = report["targets"]["can_frame"], report["targets"]["control_request"]
    assert c["kind"] == "C (libFuzzer, fast build)" and c["executions"] > 1000 and c["workers"] == 2
    seeds = len(list((fc.FUZZ / "corpus" / "can_frame").iterdir()))
    assert c["replay"]["executions"] >= seeds and not c["replay"]["crashed"]
    assert (fc.BUILD / "fast" / "can_frame").exists()
    assert py["kind"] == "Python (atheris)" and "replay" not in py and py["executions"] > 0
    # --keep: what the runs found beyond the seeds (3 s of can_frame always finds some) went
    # into the repository's grown folder, through a merge that ran every input once
    for name in ("can_frame", "control_request"):
        r = report["targets"][name]
        kept = sorted((tmp_path / "grown" / name).iterdir()) if r["kept"]["total"] else []
        assert r["kept"]["total"] == len(kept) and "keep_error" not in r
    assert report["targets"]["can_frame"]["kept"]["kept"] > 0


def _fake_merger(path, status=0):
    # libFuzzer's -merge=1: the first corpus folder gets what the others add; here one
    # input of its own name, and the arguments written down
    path.write_text("#!/bin/sh\necho \"$@\" >> \"$0.args\"\n"
                    "for a in \"$@\"; do case \"$a\" in -*) ;; *) echo new > \"$a/feed$1\"; break;; esac; done\n"
                    f"echo 'MERGE-INNER: using the control file'\necho 'MERGE-OUTER: 1 new files'\nexit {status}\n")
    path.chmod(path.stat().st_mode | stat.S_IEXEC)
    return path


def test_keep_adds_only_inputs_the_repository_does_not_hold(sandbox, monkeypatch):
    monkeypatch.setattr(fc, "GROWN", sandbox / "grown")
    (sandbox / "build" / "corpus" / "can_frame").mkdir(parents=True)
    merger = _fake_merger(sandbox / "merge")
    assert fc.keep_corpus("can_frame", merger) == {"kept": 1, "total": 1}
    assert [p.name for p in (sandbox / "grown" / "can_frame").iterdir()] == ["feed-merge=1"]
    args = (sandbox / "merge.args").read_text().split()
    seeds = fc.FUZZ / "corpus" / "can_frame"
    assert args[0] == "-merge=1" and args[-1] == str(sandbox / "build" / "corpus" / "can_frame")
    assert not any(a == str(seeds) for a in args)          # the seeds are copied, never written into
    # the same input again: the repository holds it now, nothing added
    assert fc.keep_corpus("can_frame", merger) == {"kept": 0, "total": 1}
    # the next run reads the kept inputs beside the seeds
    assert fc.command("can_frame", merger, 1, None)[-2:] == [str(seeds), str(sandbox / "grown" / "can_frame")]


def test_a_failed_merge_is_one_line_and_adds_nothing(sandbox, monkeypatch):
    monkeypatch.setattr(fc, "GROWN", sandbox / "grown")
    with pytest.raises(fc.FuzzError, match=r"can_frame: merging its corpus failed \(exit 3\)"):
        fc.keep_corpus("can_frame", _fake_merger(sandbox / "merge", status=3))
    assert not (sandbox / "grown").exists()


def test_a_merge_whose_inner_process_never_ran_is_a_failure(sandbox, monkeypatch):
    # libFuzzer's outer process runs argv[0] again; when that cannot run it says
    # "0 new files" and exits 0: that must not pass for a merge that found nothing
    monkeypatch.setattr(fc, "GROWN", sandbox / "grown")
    outer = sandbox / "outer"
    outer.write_text("#!/bin/sh\necho 'sh: 1: fuzz/x.py: Permission denied'\n"
                     "echo 'MERGE-OUTER: 0 new files with 0 new features added'\nexit 0\n")
    outer.chmod(outer.stat().st_mode | stat.S_IEXEC)
    with pytest.raises(fc.FuzzError, match="the inner process did not run .*Permission denied"):
        fc.keep_corpus("can_frame", outer)


def test_workers_share_the_runs_and_one_finding_stops_the_others(sandbox):
    # the first worker finds something after a moment; the second would run for a minute
    script = sandbox / "fuzzer"
    script.write_text(
        "#!/bin/sh\necho \"$@\" >> \"$0.args\"\n"
        "if mkdir \"$0.first\" 2>/dev/null; then\n"
        "  sleep 0.5\n"
        "  echo '#900\tpulse  cov: 30 ft: 40 corp: 5/20b lim: 4 exec/s: 900 rss: 30Mb'\n"
        "  echo 'runtime error: shift exponent 70 is too large for 64-bit type'\n"
        f"  echo 'Test unit written to {sandbox}/crashes/can_frame/crash-1'\n"
        "  exit 1\n"
        "fi\n"
        "echo '#4000\tpulse  cov: 31 ft: 39 corp: 6/24b lim: 4 exec/s: 4000 rss: 30Mb'\n"
        "exec sleep 60\n")
    script.chmod(script.stat().st_mode | stat.S_IEXEC)
    t0 = time.monotonic()
    res = fc.run_target("can_frame", script, None, 1001, workers=2)
    assert time.monotonic() - t0 < 30, "the second worker was not stopped"
    args = (sandbox / "fuzzer.args").read_text().splitlines()
    assert len(args) == 2 and all("-runs=501" in a.split() for a in args)
    assert res["workers"] == 2 and len(res["logs"]) == 2
    assert res["executions"] == 4900 and res["cov"] == 31 and res["ft"] == 40
    assert res["crashed"] and res["exit"] == 1
    assert res["inputs"] == [f"{sandbox}/crashes/can_frame/crash-1"]
    assert any("shift exponent" in f for f in res["findings"])


def test_workers_that_all_finish_are_clean(sandbox):
    fast = _fake_fuzzer(sandbox / "fast", FAST_OK, 0)
    res = fc.run_target("can_frame", fast, None, 10000, workers=3)
    assert not res["crashed"] and res["executions"] == 15000 and res["exit"] == 0
    assert all("-runs=3334" in a.split() for a in (sandbox / "fast.args").read_text().splitlines())


def test_a_stop_signal_keeps_the_figures_and_is_no_finding(sandbox, monkeypatch):
    # a fuzzer that prints its figures when interrupted, as libFuzzer does (exit 72); like
    # libFuzzer it installs its SIGINT handler itself (a shell's trap cannot, when the
    # test runs under a parent that ignores SIGINT, as a job started in the background
    # does), and says when it has (a ready file each): only then the stop comes
    ready = sandbox / "ready"
    ready.mkdir()
    script = sandbox / "fuzzer"
    script.write_text(f"#!{sys.executable}\n"
                      "import os, signal, sys, time\n"
                      "def stop(*_):\n"
                      "    print('==1== libFuzzer: run interrupted; exiting')\n"
                      "    print('stat::number_of_executed_units: 7100', flush=True)\n"
                      "    os._exit(72)\n"
                      "signal.signal(signal.SIGINT, stop)\n"
                      "print('#7000\\tpulse  cov: 30 ft: 40 corp: 5/20b lim: 4 exec/s: 7000 rss: 30Mb',"
                      " flush=True)\n"
                      f"open(os.path.join({str(ready)!r}, str(os.getpid())), 'w').close()\n"
                      "time.sleep(60)\n")
    script.chmod(script.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setattr(fc, "_STOP", threading.Event())

    stopped_at = []

    def stop_when_ready():
        deadline = time.monotonic() + 30.0
        while len(list(ready.iterdir())) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        stopped_at.append(time.monotonic())
        fc._STOP.set()

    threading.Thread(target=stop_when_ready, daemon=True).start()
    res = fc.run_target("can_frame", script, None, 10**8, workers=2, checked=script)
    assert len(list(ready.iterdir())) == 2
    assert time.monotonic() - stopped_at[0] < fc.STOP_GRACE_S      # stopped by the signal, not killed
    assert res["interrupted"] and not res["crashed"] and res["findings"] == []
    assert res["executions"] == 14200 and "replay" not in res


def test_the_campaign_ledger_adds_run_after_run(sandbox):
    r = {"executions": 1000, "seconds": 1.0, "cov": 5, "ft": 6, "findings": []}
    assert fc.record_campaign({"can_frame": r}, "fast", 2)["can_frame"][:2] == (1000, 1)
    total = fc.record_campaign({"can_frame": dict(r, executions=250, interrupted=True),
                                "xcp_packet": r}, "fast", 1)
    assert total["can_frame"][:2] == (1250, 2) and total["xcp_packet"][:2] == (1000, 1)
    book = json.loads((sandbox / "build" / "ledger.json").read_text())
    assert [x["interrupted"] for x in book["can_frame"]["runs"]] == [False, True]
    assert book["xcp_packet"]["runs"][0]["build"] == "atheris"
    (sandbox / "build" / "ledger.json").write_text("not json")       # a damaged ledger starts anew
    assert fc.record_campaign({"can_frame": r}, "checked", 1)["can_frame"][:2] == (1000, 1)
