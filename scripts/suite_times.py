"""The test suite's own figures: each stage's wall time and the slowest tests.

    python scripts/suite_times.py [--elapsed S] OUT.json TIER STAGE=STATUS:WALL_S[:JUNIT.xml[:FIGURES]] ...

Called by scripts/test and scripts/test-long at their end (also after a
failed stage): reads the JUnit XML each pytest stage wrote (the time of a
test case there is its setup, call and teardown together), prints a table of
the stages and the slowest tests, and writes OUT.json:

    {"tier": "quick|full|long", "finished": ISO time, "total_s": ..., "elapsed_s": ...,
     "stages": [{"name", "status", "wall_s", "tests", "failed", "skipped", "figures"}],
     "slowest": [{"test", "stage", "time_s"}]}         (the 20 slowest)

FIGURES is the path of a stage's own figures (the soak's JSON, the fuzz
table), given in its entry with "figures_found". total_s is the sum of the stages' wall times; elapsed_s (--elapsed, the
run's own clock) is less when stages ran side by side (the guest beside the
host tests). A stage that does not
exist in a run (the guest stage of --quick) is simply not named. Exit status 0; a missing or unreadable XML is reported in the
stage's entry ("junit": "missing"), never fatal: the figures must not hide
the tests' own result.
"""

import datetime
import json
import os
import sys
import xml.etree.ElementTree as ET

SLOWEST = 20


def _cases(path, stage):
    root = ET.parse(path).getroot()
    suites = [root] if root.tag == "testsuite" else list(root.iter("testsuite"))
    cases, failed, skipped = [], 0, 0
    for suite in suites:
        for case in suite.iter("testcase"):
            name = f"{case.get('classname', '')}::{case.get('name', '')}".lstrip(":")
            cases.append({"test": name, "stage": stage, "time_s": float(case.get("time") or 0.0)})
            if case.find("failure") is not None or case.find("error") is not None:
                failed += 1
            elif case.find("skipped") is not None:
                skipped += 1
    return cases, failed, skipped


def main(argv):
    elapsed = None
    if argv[:1] == ["--elapsed"] and len(argv) > 1:
        elapsed, argv = round(float(argv[1]), 1), argv[2:]
    if len(argv) < 3:
        print(__doc__.split("\n\n")[1], file=sys.stderr)
        return 2
    out, tier, specs = argv[0], argv[1], argv[2:]
    stages, cases = [], []
    for spec in specs:
        name, _, rest = spec.partition("=")
        status, _, rest = rest.partition(":")
        wall, _, rest = rest.partition(":")
        junit, _, figures = rest.partition(":")
        stage = {"name": name, "status": status, "wall_s": round(float(wall), 1)}
        if figures:
            stage.update(figures=figures, figures_found=os.path.exists(figures))
        if junit:
            try:
                found, failed, skipped = _cases(junit, name)
            except (OSError, ET.ParseError) as e:
                stage["junit"] = f"missing ({e.__class__.__name__}: {junit})"
            else:
                stage.update(tests=len(found), failed=failed, skipped=skipped)
                cases += found
        stages.append(stage)
    cases.sort(key=lambda c: -c["time_s"])
    total = round(sum(s["wall_s"] for s in stages), 1)
    report = {"tier": tier,
              "finished": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
              "total_s": total, "elapsed_s": elapsed if elapsed is not None else total,
              "stages": stages,
              "slowest": [dict(c, time_s=round(c["time_s"], 2)) for c in cases[:SLOWEST]]}
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    with open(out, "w", encoding="utf-8") as f:
        json.dump(report, f, indent=1)
        f.write("\n")

    print(f"\n{'stage':<10}{'status':>8}{'wall':>10}{'tests':>8}")
    for s in stages:
        tests = s.get("tests", "")
        print(f"{s['name']:<10}{s['status']:>8}{s['wall_s']:>9.1f}s{tests!s:>8}")
    print(f"{'total':<10}{'':>8}{total:>9.1f}s   ({total / 60:.1f} min, tier {tier})")
    if elapsed is not None and elapsed < total - 1.0:
        print(f"{'elapsed':<10}{'':>8}{elapsed:>9.1f}s   ({elapsed / 60:.1f} min: stages side by side)")
    if cases:
        print("slowest tests (setup + call + teardown):")
        for c in cases[:10]:
            print(f"  {c['time_s']:7.1f} s  {c['stage']:<6} {c['test']}")
    print(f"figures in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
