/*
 * fmi2.c - the FMI 2.0 co-simulation interface of the plant.
 *
 * A thin layer: each function checks the shape of its arguments, turns the
 * FMI 2 types into those of fmu_instance.h and calls it (which checks the
 * instance handle); the saved-state functions are FMU_STATE_FUNCTIONS,
 * written once for FMI 2 and FMI 3 in fmu_instance.h. The only FMI 2
 * specific behaviour here is the logger (a printf-like callback) and the
 * status queries of asynchronous steps, which this FMU never makes.
 */
#include <stdio.h>
#include <string.h>

#include "fmi2_platform.h"
#include "fmu_instance.h"

/* The FMI 2 logger is printf-like: its message is a format. Every '%' of
 * the text is doubled, so the text is a format without conversions: a
 * logger that formats prints it as it is, and so does one that cannot read
 * variadic arguments and prints the format (a Python ctypes callback). */
static void emit2(const fmu_logger *lg, fmu_status status, const char *category,
                  const char *message)
{
    fmi2CallbackLogger logger = (fmi2CallbackLogger)lg->callback;
    char format[2 * FMU_MESSAGE_MAX];
    size_t k = 0;
    for (const char *p = message; *p != '\0' && k + 2 < sizeof format; p++) {
        if (*p == '%')
            format[k++] = '%';
        format[k++] = *p;
    }
    format[k] = '\0';
    logger(lg->environment, lg->name, (fmi2Status)status, category, format);
}

/* ------------------------------------------------------------------ */
/* Common functions                                                    */
/* ------------------------------------------------------------------ */

const char *fmi2GetTypesPlatform(void)
{
    return FMI2_TYPES_PLATFORM;
}

const char *fmi2GetVersion(void)
{
    return FMI2_VERSION;
}

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean loggingOn, size_t nCategories,
                               const fmi2String categories[])
{
    return (fmi2Status)fmu_set_debug_logging(c, "fmi2SetDebugLogging", loggingOn != fmi2False,
                                             nCategories, categories);
}

fmi2Component fmi2Instantiate(fmi2String instanceName, fmi2Type fmuType, fmi2String fmuGUID,
                              fmi2String fmuResourceLocation,
                              const fmi2CallbackFunctions *functions, fmi2Boolean visible,
                              fmi2Boolean loggingOn)
{
    static const char fn[] = "fmi2Instantiate";
    (void)fmuResourceLocation; /* the FMU needs no resources: all is compiled in */
    (void)visible;             /* no user interface */
    /* the standard requires a logger; without one a refusal could not be told */
    if (functions == NULL || functions->logger == NULL)
        return NULL;
    fmu_logger lg;
    memset(&lg, 0, sizeof lg);
    lg.emit = emit2;
    lg.callback = (void (*)(void))functions->logger;
    lg.environment = functions->componentEnvironment;
    lg.logging_on = loggingOn != fmi2False;
    lg.log_events = 1;
    snprintf(lg.name, sizeof lg.name, "%s", instanceName ? instanceName : "");
    if (instanceName == NULL || instanceName[0] == '\0') {
        fmu_log(&lg, FMU_ERROR, fn, "instanceName is empty");
        return NULL;
    }
    if (fmuType != fmi2CoSimulation) {
        fmu_log(&lg, FMU_ERROR, fn,
                "fmuType %d refused: this FMU is for co-simulation only (fmi2CoSimulation)",
                (int)fmuType);
        return NULL;
    }
    return fmu_instance_new(&lg, fn, "GUID", fmuGUID);
}

void fmi2FreeInstance(fmi2Component c)
{
    fmu_instance_free(c);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime)
{
    (void)toleranceDefined; /* fixed-step explicit Euler: no tolerance to meet */
    (void)tolerance;
    return (fmi2Status)fmu_setup_experiment(c, "fmi2SetupExperiment", startTime,
                                            stopTimeDefined != fmi2False, stopTime);
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c)
{
    return (fmi2Status)fmu_enter_initialization(c, "fmi2EnterInitializationMode");
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c)
{
    return (fmi2Status)fmu_exit_initialization(c, "fmi2ExitInitializationMode");
}

fmi2Status fmi2Terminate(fmi2Component c)
{
    return (fmi2Status)fmu_terminate(c, "fmi2Terminate");
}

fmi2Status fmi2Reset(fmi2Component c)
{
    return (fmi2Status)fmu_reset(c, "fmi2Reset");
}

/* ------------------------------------------------------------------ */
/* Getting and setting variables                                       */
/* ------------------------------------------------------------------ */

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       fmi2Real value[])
{
    if (nvr > 0 && (vr == NULL || value == NULL))
        return (fmi2Status)fmu_error(c, "fmi2GetReal", "vr or value is NULL");
    return (fmi2Status)fmu_get_reals(c, "fmi2GetReal", vr, nvr, value);
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       const fmi2Real value[])
{
    if (nvr > 0 && (vr == NULL || value == NULL))
        return (fmi2Status)fmu_error(c, "fmi2SetReal", "vr or value is NULL");
    return (fmi2Status)fmu_set_reals(c, "fmi2SetReal", vr, nvr, value);
}

/* This FMU has Real variables only: any value reference given to the
 * Integer, Boolean or String functions names no variable of that type. */
#define NO_VARIABLES(Type)                                                                      \
    fmi2Status fmi2Get##Type(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,        \
                             fmi2##Type value[])                                                \
    {                                                                                           \
        (void)value;                                                                            \
        return (fmi2Status)fmu_no_variables(c, "fmi2Get" #Type, vr, nvr, "vr", #Type, "Real");  \
    }                                                                                           \
    fmi2Status fmi2Set##Type(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,        \
                             const fmi2##Type value[])                                          \
    {                                                                                           \
        (void)value;                                                                            \
        return (fmi2Status)fmu_no_variables(c, "fmi2Set" #Type, vr, nvr, "vr", #Type, "Real");  \
    }

NO_VARIABLES(Integer)
NO_VARIABLES(Boolean)
NO_VARIABLES(String)

/* ------------------------------------------------------------------ */
/* FMU states                                                          */
/* ------------------------------------------------------------------ */

FMU_STATE_FUNCTIONS(fmi2Status, fmi2Component, fmi2FMUstate, fmi2Byte, fmi2GetFMUstate,
                    fmi2SetFMUstate, fmi2FreeFMUstate, fmi2SerializedFMUstateSize,
                    fmi2SerializeFMUstate, fmi2DeSerializeFMUstate)

/* ------------------------------------------------------------------ */
/* Derivatives (not provided)                                          */
/* ------------------------------------------------------------------ */

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference vUnknown_ref[],
                                        size_t nUnknown, const fmi2ValueReference vKnown_ref[],
                                        size_t nKnown, const fmi2Real dvKnown[],
                                        fmi2Real dvUnknown[])
{
    (void)vUnknown_ref, (void)nUnknown, (void)vKnown_ref, (void)nKnown, (void)dvKnown,
        (void)dvUnknown;
    return (fmi2Status)fmu_unsupported(c, "fmi2GetDirectionalDerivative",
                                       "the FMU provides no directional derivatives");
}

fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[])
{
    (void)vr, (void)nvr, (void)order, (void)value;
    return (fmi2Status)fmu_unsupported(c, "fmi2SetRealInputDerivatives",
                                       "the FMU holds its inputs over a step (it cannot "
                                       "interpolate them)");
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[],
                                        size_t nvr, const fmi2Integer order[], fmi2Real value[])
{
    (void)vr, (void)nvr, (void)order, (void)value;
    return (fmi2Status)fmu_unsupported(c, "fmi2GetRealOutputDerivatives",
                                       "the FMU provides no output derivatives");
}

/* ------------------------------------------------------------------ */
/* Co-simulation                                                       */
/* ------------------------------------------------------------------ */

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint,
                      fmi2Real communicationStepSize, fmi2Boolean noSetFMUStatePriorToCurrentPoint)
{
    (void)noSetFMUStatePriorToCurrentPoint; /* a saved state is a full copy: nothing to drop */
    double reached;
    return (fmi2Status)fmu_do_step(c, "fmi2DoStep", currentCommunicationPoint,
                                   communicationStepSize, &reached);
}

/* DoStep runs to completion before it returns (never fmi2Pending): there is
 * no step to cancel and no asynchronous status to ask for. */
#define NOT_PENDING "no step is pending (fmi2DoStep never returns fmi2Pending)"

fmi2Status fmi2CancelStep(fmi2Component c)
{
    return (fmi2Status)fmu_error(c, "fmi2CancelStep", NOT_PENDING);
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value)
{
    (void)value;
    return (fmi2Status)fmu_error(c, "fmi2GetStatus",
                                 s == fmi2DoStepStatus ? "fmi2DoStepStatus: " NOT_PENDING
                                                       : "this status kind is not an fmi2Status");
}

/* The two status queries this FMU answers, each of one kind: the time the
 * last step reached (Real, fmi2LastSuccessfulTime) and whether the plant
 * asks to end the simulation (Boolean, fmi2Terminated). value: the
 * caller's, of the kind's type. */
static fmi2Status answer_status(fmi2Component c, const char *fn, fmi2StatusKind s,
                                fmi2StatusKind kind, void *value)
{
    if (!fmu_instance_ok(c))
        return fmi2Error;
    if (s != kind)
        return (fmi2Status)fmu_error(c, fn, kind == fmi2Terminated
                                                ? "only fmi2Terminated is a Boolean status"
                                                : "only fmi2LastSuccessfulTime is a Real status");
    if (value == NULL)
        return (fmi2Status)fmu_error(c, fn, "value is NULL");
    if (kind == fmi2Terminated)
        *(fmi2Boolean *)value = fmi2False; /* the plant never asks to end the simulation */
    else /* after a failed step: the last time with a finite state */
        *(fmi2Real *)value = fmu_time(c);
    return fmi2OK;
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value)
{
    return answer_status(c, "fmi2GetRealStatus", s, fmi2LastSuccessfulTime, value);
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value)
{
    (void)s, (void)value;
    return (fmi2Status)fmu_error(c, "fmi2GetIntegerStatus", "FMI 2 defines no Integer status");
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value)
{
    return answer_status(c, "fmi2GetBooleanStatus", s, fmi2Terminated, value);
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value)
{
    (void)s, (void)value;
    return (fmi2Status)fmu_error(c, "fmi2GetStringStatus", "fmi2PendingStatus: " NOT_PENDING);
}
