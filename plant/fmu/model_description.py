"""modelDescription.xml (FMI 2.0 and 3.0 co-simulation) and FMI 3's
sources/buildDescription.xml, written from the FMU's variables
(``plant.fmu.variables``)."""

from __future__ import annotations

import datetime
import math
from xml.sax.saxutils import quoteattr

from plant.fmu.variables import INPUT, OUTPUT, TIME, Model, Variable

MODEL_IDENTIFIER = "dct_plant"
MODEL_NAME = "dct_hil.plant"
GENERATION_TOOL = "dct-hil fmu"
LOG_CATEGORIES = (("logStatusWarning", "warnings: a request the FMU changed or ignored"),
                  ("logStatusError", "errors: a request refused, the plant's own errors"),
                  ("logEvents", "initialization, reset, termination"))

_PI = math.pi
#: SI exponents (kg, m, s, A, rad) and factor of each unit the names use
_BASE_UNITS = {
    "%": ({}, 0.01), "A": ({"A": 1}, 1.0), "N": ({"kg": 1, "m": 1, "s": -2}, 1.0),
    "N m s/rad": ({"kg": 1, "m": 2, "s": -1, "rad": -1}, 1.0),
    "N s/m": ({"kg": 1, "s": -1}, 1.0), "N/A": ({"kg": 1, "m": 1, "s": -2, "A": -1}, 1.0),
    "N/m": ({"kg": 1, "s": -2}, 1.0), "Nm": ({"kg": 1, "m": 2, "s": -2}, 1.0),
    "Nm/(rpm s)": ({"kg": 1, "m": 2, "s": -2, "rad": -1}, 60.0 / (2 * _PI)),
    "Nm/rad": ({"kg": 1, "m": 2, "s": -2, "rad": -1}, 1.0),
    "Nm/rpm": ({"kg": 1, "m": 2, "s": -1, "rad": -1}, 60.0 / (2 * _PI)),
    "Pa": ({"kg": 1, "m": -1, "s": -2}, 1.0), "W": ({"kg": 1, "m": 2, "s": -3}, 1.0),
    "bar": ({"kg": 1, "m": -1, "s": -2}, 1e5), "cm3": ({"m": 3}, 1e-6),
    "deg": ({"rad": 1}, _PI / 180.0), "g/kWh": ({"m": -2, "s": 2}, 1e-3 / 3.6e6),
    "kg": ({"kg": 1}, 1.0), "kg m2": ({"kg": 1, "m": 2}, 1.0),
    "kg/l": ({"kg": 1, "m": -3}, 1e3), "kg/m3": ({"kg": 1, "m": -3}, 1.0),
    "km/h": ({"m": 1, "s": -1}, 1 / 3.6), "l": ({"m": 3}, 1e-3),
    "l/h": ({"m": 3, "s": -1}, 1e-3 / 3600.0), "m": ({"m": 1}, 1.0),
    "m/s": ({"m": 1, "s": -1}, 1.0), "m/s2": ({"m": 1, "s": -2}, 1.0), "m2": ({"m": 2}, 1.0),
    "m2/s": ({"m": 2, "s": -1}, 1.0), "m3/s/Pa": ({"kg": -1, "m": 4, "s": 1}, 1.0),
    "mm": ({"m": 1}, 1e-3), "rad/s": ({"rad": 1, "s": -1}, 1.0),
    "rpm": ({"rad": 1, "s": -1}, 2 * _PI / 60.0), "s": ({"s": 1}, 1.0),
    "kW": ({"kg": 1, "m": 2, "s": -3}, 1e3), "kPa": ({"kg": 1, "m": -1, "s": -2}, 1e3),
    "m/s/s": ({"m": 1, "s": -2}, 1.0), "ms": ({"s": 1}, 1e-3), "us": ({"s": 1}, 1e-6),
    "rad": ({"rad": 1}, 1.0), "mA": ({"A": 1}, 1e-3), "V": ({"kg": 1, "m": 2, "s": -3, "A": -1}, 1.0),
}


def _num(x: float) -> str:
    return repr(float(x))


def _units(model: Model) -> list[str]:
    used = sorted({v.unit for v in model.variables if v.unit})
    out = ["  <UnitDefinitions>"]
    for unit in used:
        base = _BASE_UNITS.get(unit)
        if base is None:
            out.append(f"    <Unit name={quoteattr(unit)}/>")
            continue
        exps, factor = base
        attrs = "".join(f' {k}="{e}"' for k, e in exps.items())
        if factor != 1.0:
            attrs += f' factor="{_num(factor)}"'
        out.append(f"    <Unit name={quoteattr(unit)}>\n      <BaseUnit{attrs}/>\n    </Unit>")
    out.append("  </UnitDefinitions>")
    return out


def _log_categories() -> list[str]:
    out = ["  <LogCategories>"]
    out += [f"    <Category name={quoteattr(n)} description={quoteattr(d)}/>"
            for n, d in LOG_CATEGORIES]
    out.append("  </LogCategories>")
    return out


def _common_attrs(v: Variable) -> str:
    a = f"name={quoteattr(v.name)} valueReference=\"{v.vr}\""
    if v.description:
        a += f" description={quoteattr(v.description)}"
    return a + f' causality="{v.causality}" variability="{v.variability}"'


def _type_attrs(v: Variable) -> str:
    a = ""
    if v.unit:
        a += f" unit={quoteattr(v.unit)}"
    if math.isfinite(v.min):
        a += f' min="{_num(v.min)}"'
    if math.isfinite(v.max):
        a += f' max="{_num(v.max)}"'
    if v.kind not in (TIME, OUTPUT):
        a += f' start="{_num(v.start)}"'
    return a


def _initial(v: Variable) -> str:
    if v.kind in (TIME, INPUT):
        return ""
    return ' initial="calculated"' if v.kind == OUTPUT else ' initial="exact"'


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def _description(model: Model) -> str:
    car = model.params_path or "the default car (plant/data/golf_mk5_gti_dsg.toml)"
    return (f"Dual clutch transmission powertrain (engine, DSG 02E with clutch hydraulics and "
            f"synchronizers, driveline, vehicle), fixed internal step {model.step_s * 1e3:g} ms; "
            f"parameters: {car}")


def fmi2(model: Model, source_files: list[str], version: str = "") -> str:
    """FMI 2.0 modelDescription.xml (co-simulation; source files named)."""
    out = ['<?xml version="1.0" encoding="UTF-8"?>',
           f'<fmiModelDescription fmiVersion="2.0" modelName="{MODEL_NAME}" '
           f'guid="{model.token}" description={quoteattr(_description(model))} '
           f'generationTool={quoteattr(GENERATION_TOOL + (" " + version if version else ""))} '
           f'generationDateAndTime="{_now()}" variableNamingConvention="structured" '
           f'numberOfEventIndicators="0">',
           f'  <CoSimulation modelIdentifier="{MODEL_IDENTIFIER}" '
           f'canHandleVariableCommunicationStepSize="true" canGetAndSetFMUstate="true" '
           f'canSerializeFMUstate="true" canNotUseMemoryManagementFunctions="true">',
           "    <SourceFiles>"]
    out += [f"      <File name={quoteattr(f)}/>" for f in source_files]
    out += ["    </SourceFiles>", "  </CoSimulation>"]
    out += _units(model)
    out += _log_categories()
    out.append('  <DefaultExperiment startTime="0.0" stopTime="10.0" stepSize="0.01"/>')
    out.append("  <ModelVariables>")
    for v in model.variables:
        out.append(f"    <ScalarVariable {_common_attrs(v)}{_initial(v)}>")
        out.append(f"      <Real{_type_attrs(v)}/>")
        out.append("    </ScalarVariable>")
    out.append("  </ModelVariables>")
    outputs = [v for v in model.variables if v.kind == OUTPUT]
    out.append("  <ModelStructure>")
    out.append("    <Outputs>")
    out += [f'      <Unknown index="{v.vr + 1}"/>' for v in outputs]
    out.append("    </Outputs>")
    out.append("    <InitialUnknowns>")
    out += [f'      <Unknown index="{v.vr + 1}"/>' for v in outputs]
    out.append("    </InitialUnknowns>")
    out.append("  </ModelStructure>")
    out.append("</fmiModelDescription>")
    return "\n".join(out) + "\n"


def fmi3(model: Model, version: str = "") -> str:
    """FMI 3.0 modelDescription.xml (co-simulation)."""
    out = ['<?xml version="1.0" encoding="UTF-8"?>',
           f'<fmiModelDescription fmiVersion="3.0" modelName="{MODEL_NAME}" '
           f'instantiationToken="{model.token}" description={quoteattr(_description(model))} '
           f'generationTool={quoteattr(GENERATION_TOOL + (" " + version if version else ""))} '
           f'generationDateAndTime="{_now()}" variableNamingConvention="structured">',
           f'  <CoSimulation modelIdentifier="{MODEL_IDENTIFIER}" canGetAndSetFMUState="true" '
           f'canSerializeFMUState="true" canHandleVariableCommunicationStepSize="true" '
           f'fixedInternalStepSize="{_num(model.step_s)}" hasEventMode="false"/>']
    out += _units(model)
    out += _log_categories()
    out.append('  <DefaultExperiment startTime="0.0" stopTime="10.0" stepSize="0.01"/>')
    out.append("  <ModelVariables>")
    for v in model.variables:
        out.append(f"    <Float64 {_common_attrs(v)}{_initial(v)}{_type_attrs(v)}/>")
    out.append("  </ModelVariables>")
    outputs = [v for v in model.variables if v.kind == OUTPUT]
    out.append("  <ModelStructure>")
    out += [f'    <Output valueReference="{v.vr}"/>' for v in outputs]
    out += [f'    <InitialUnknown valueReference="{v.vr}"/>' for v in outputs]
    out.append("  </ModelStructure>")
    out.append("</fmiModelDescription>")
    return "\n".join(out) + "\n"


def build_description(source_files: list[str]) -> str:
    """FMI 3.0 sources/buildDescription.xml: one C99 file set, sources/ included."""
    out = ['<?xml version="1.0" encoding="UTF-8"?>',
           '<fmiBuildDescription fmiVersion="3.0">',
           f'  <BuildConfiguration modelIdentifier="{MODEL_IDENTIFIER}" '
           f'description="the plant core and the FMI 3.0 layer; link with the math library (-lm)">',
           '    <SourceFileSet language="C99">']
    out += [f"      <SourceFile name={quoteattr(f)}/>" for f in source_files]
    out += ['      <IncludeDirectory name="."/>',
            "    </SourceFileSet>",
            '    <Library name="m" external="true" description="the C math library (libm)"/>',
            "  </BuildConfiguration>",
            "</fmiBuildDescription>"]
    return "\n".join(out) + "\n"
