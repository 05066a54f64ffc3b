"""``dct-hil fmu OUT.fmu [--fmi 2|3] [--params FILE.toml]``: the plant as a
co-simulation FMU.

The FMU holds the plant's own C core (``plant/csrc/``, the files the Python
extension is built from) and the FMI layer (``plant/fmu/csrc/``), compiled
with the system's C compiler (``$CC``, else ``cc``) with the extension's
flags, so the FMU computes what ``dct-hil simulate`` computes, bit for bit.
Layout::

    modelDescription.xml
    binaries/linux64/dct_plant.so          (FMI 2)  or  binaries/x86_64-linux/ (FMI 3)
    sources/*.c *.h                        the same files, and fmu_variables.c
    sources/buildDescription.xml           (FMI 3; FMI 2 lists them in modelDescription.xml)
    documentation/index.html
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

from plant.fmu import model_description as md
from plant.fmu import variables

_PLANT_CSRC = Path(__file__).resolve().parents[1] / "csrc"
_FMU_CSRC = Path(__file__).resolve().parent / "csrc"
#: what the core needs of plant/csrc (dct_bench.c: the benchmark, not the model)
_CORE_EXCLUDED = {"dct_bench.c", "dct_bench.h"}
#: the flags of the Python extension (plant/_build.py): the same arithmetic
COMPILE_FLAGS = ["-O2", "-std=c11", "-fno-math-errno", "-fPIC", "-shared", "-fvisibility=hidden"]
FMI_VERSIONS = (2, 3)


@dataclass
class BuildResult:
    path: str
    fmi_version: int
    variables: int
    binary: str            # path inside the FMU
    token: str


def platform_dir(fmi_version: int) -> str:
    """binaries/<this>: FMI 2's name (linux64, linux32) or FMI 3's
    (<architecture>-linux)."""
    machine = platform.machine().lower()
    arch = {"amd64": "x86_64", "x86_64": "x86_64", "aarch64": "aarch64", "arm64": "aarch64",
            "i686": "x86", "i386": "x86"}.get(machine, machine)
    if not sys.platform.startswith("linux"):
        raise variables.FmuError(f"building the FMU's binary needs Linux, not {sys.platform}")
    if fmi_version == 2:
        if arch == "x86_64":
            return "linux64"
        if arch == "x86":
            return "linux32"
        raise variables.FmuError(f"FMI 2 names no platform for {machine} "
                                 "(linux64 and linux32 only): build with --fmi 3")
    return f"{arch}-linux"


def source_files(fmi_version: int) -> list[tuple[Path | None, str]]:
    """(file to copy or None for the generated table, name in sources/)."""
    out: list[tuple[Path | None, str]] = []
    for p in sorted(_PLANT_CSRC.iterdir()):
        if p.suffix in (".c", ".h") and p.name not in _CORE_EXCLUDED:
            out.append((p, p.name))
    own = ["fmu_model.h", "fmu_instance.h", "fmu_instance.c",
           f"fmi{fmi_version}_platform.h", f"fmi{fmi_version}.c"]
    for name in own:
        out.append((_FMU_CSRC / name, name))
    out.append((None, "fmu_variables.c"))
    return out


def _compiler() -> list[str]:
    cc = shlex.split(os.environ.get("CC", "").strip()) or ["cc"]
    if shutil.which(cc[0]) is None:
        raise variables.FmuError(f"no C compiler: {cc[0]!r} not found (install gcc, or set CC)")
    return cc


def compile_binary(sources_dir: Path, out_so: Path) -> None:
    """Compiles every .c of ``sources_dir`` into ``out_so``; a failure raises
    FmuError with the compiler's first error line."""
    c_files = sorted(str(p) for p in sources_dir.glob("*.c"))
    cmd = _compiler() + COMPILE_FLAGS + ["-I", str(sources_dir), "-o", str(out_so)] + c_files
    cmd.append("-lm")
    try:
        run = subprocess.run(cmd, capture_output=True, text=True, check=False)
    except OSError as e:
        raise variables.FmuError(f"cannot run the C compiler: {e}") from None
    if run.returncode != 0:
        lines = [ln for ln in run.stderr.splitlines() if "error" in ln] or run.stderr.splitlines()
        raise variables.FmuError("compiling the FMU failed: "
                                 + (lines[0].strip() if lines else f"exit {run.returncode}"))


def _version() -> str:
    try:
        from importlib.metadata import PackageNotFoundError, version
        return version("dct-hil")
    except (ImportError, PackageNotFoundError):
        return ""


def _documentation(model: variables.Model, fmi_version: int) -> str:
    n = {k: sum(1 for v in model.variables if v.kind == k) for k in range(6)}
    return f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>{md.MODEL_NAME}</title></head><body>
<h1>{md.MODEL_NAME}: FMI {fmi_version}.0 co-simulation</h1>
<p>{md._description(model)}.</p>
<ul>
<li>{n[variables.INPUT]} inputs (held over a communication step), {n[variables.OUTPUT]} outputs,
{n[variables.PARAM_FIXED]} fixed and {n[variables.PARAM_TUNABLE]} tunable parameters
(faults included), {n[variables.INITIAL]} initial conditions.</li>
<li>The communication step must be a whole multiple of {model.step_s * 1e3:g} ms;
the FMU's state can be got, set and serialized.</li>
<li>Inputs that are NaN or infinite are refused; parameters outside their range are refused.</li>
</ul>
</body></html>
"""


def build(out_path: str | os.PathLike, fmi_version: int = 2,
          params_path: str | os.PathLike | None = None) -> BuildResult:
    """Writes the FMU; raises FmuError or ParamError (one line) and leaves
    no partial file behind."""
    if fmi_version not in FMI_VERSIONS:
        raise variables.FmuError(f"unknown FMI version {fmi_version!r}: 2 or 3")
    out = Path(out_path)
    if out.is_dir():
        raise variables.FmuError(f"{out}: is a folder; name the .fmu file to write")
    if not out.parent.is_dir():
        raise variables.FmuError(f"{out}: folder {out.parent} does not exist")
    plat = platform_dir(fmi_version)
    model = variables.load(params_path)
    version = _version()
    files = source_files(fmi_version)
    names = [name for _, name in files if name.endswith(".c")]
    with tempfile.TemporaryDirectory(prefix="dct-fmu-") as tmp:
        root = Path(tmp)
        src = root / "sources"
        src.mkdir()
        for path, name in files:
            if path is None:
                (src / name).write_text(variables.generate_c(model=model), encoding="utf-8")
            else:
                shutil.copyfile(path, src / name)
        if fmi_version == 2:
            xml = md.fmi2(model, names, version)
        else:
            xml = md.fmi3(model, version)
            (src / "buildDescription.xml").write_text(md.build_description(names),
                                                       encoding="utf-8")
        (root / "modelDescription.xml").write_text(xml, encoding="utf-8")
        bindir = root / "binaries" / plat
        bindir.mkdir(parents=True)
        so = bindir / f"{md.MODEL_IDENTIFIER}.so"
        compile_binary(src, so)
        (root / "documentation").mkdir()
        (root / "documentation" / "index.html").write_text(_documentation(model, fmi_version),
                                                          encoding="utf-8")
        partial = out.with_name(out.name + ".part")
        try:
            with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as z:
                for p in sorted(root.rglob("*")):
                    if p.is_file():
                        z.write(p, p.relative_to(root).as_posix())
            os.replace(partial, out)
        except BaseException:
            partial.unlink(missing_ok=True)
            raise
    return BuildResult(str(out), fmi_version, len(model.variables),
                       f"binaries/{plat}/{md.MODEL_IDENTIFIER}.so", model.token)


# -- command line -------------------------------------------------------------

def _fmi_version(text: str) -> int:
    if text.strip() in ("2", "2.0"):
        return 2
    if text.strip() in ("3", "3.0"):
        return 3
    raise argparse.ArgumentTypeError(f"unknown FMI version {text!r}: 2 or 3")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", metavar="OUT.fmu", help="the FMU file to write")
    parser.add_argument("--fmi", type=_fmi_version, default=2, metavar="2|3",
                        help="FMI version (default 2)")
    parser.add_argument("--params", metavar="FILE.toml", default=None,
                        help="a car's parameter file merged over the default car: baked in as "
                             "the parameters' start values")


def run(args: argparse.Namespace, out=None, err=None, prog: str = "dct-hil fmu") -> int:
    from plant.params import ParamError
    out = out or sys.stdout
    err = err or sys.stderr
    try:
        result = build(args.out, args.fmi, args.params)
    except (variables.FmuError, ParamError) as e:
        print(f"{prog}: {e}", file=err)
        return 1
    print(f"{result.path}: FMI {result.fmi_version}.0 co-simulation FMU, {result.variables} "
          f"variables, {result.binary}", file=out)
    return 0
