/*
 * fmi2.c - the FMI 2.0 co-simulation interface of the plant.
 *
 * A thin layer: each function checks the shape of its arguments, turns the
 * FMI 2 types into those of fmu_instance.h and calls it. The only FMI 2
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

/* the instance behind c, or NULL (nothing to log with) */
static fmu_instance *instance(fmi2Component c)
{
    fmu_instance *inst = c;
    return fmu_instance_ok(inst) ? inst : NULL;
}

static fmi2Status fail(fmu_instance *inst, const char *fn, const char *what)
{
    fmu_log(&inst->logger, FMU_ERROR, fn, "%s", what);
    return fmi2Error;
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
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return (fmi2Status)fmu_set_debug_logging(inst, "fmi2SetDebugLogging", loggingOn != fmi2False,
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
    fmu_instance_free(instance(c));
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean toleranceDefined, fmi2Real tolerance,
                               fmi2Real startTime, fmi2Boolean stopTimeDefined, fmi2Real stopTime)
{
    (void)toleranceDefined; /* fixed-step explicit Euler: no tolerance to meet */
    (void)tolerance;
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return (fmi2Status)fmu_setup_experiment(inst, "fmi2SetupExperiment", startTime,
                                            stopTimeDefined != fmi2False, stopTime);
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c)
{
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return (fmi2Status)fmu_enter_initialization(inst, "fmi2EnterInitializationMode");
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c)
{
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return (fmi2Status)fmu_exit_initialization(inst, "fmi2ExitInitializationMode");
}

fmi2Status fmi2Terminate(fmi2Component c)
{
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return (fmi2Status)fmu_terminate(inst, "fmi2Terminate");
}

fmi2Status fmi2Reset(fmi2Component c)
{
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return (fmi2Status)fmu_reset(inst, "fmi2Reset");
}

/* ------------------------------------------------------------------ */
/* Getting and setting variables                                       */
/* ------------------------------------------------------------------ */

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       fmi2Real value[])
{
    static const char fn[] = "fmi2GetReal";
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    if (nvr > 0 && (vr == NULL || value == NULL))
        return fail(inst, fn, "vr or value is NULL");
    for (size_t i = 0; i < nvr; i++) {
        fmu_status st = fmu_get_real(inst, fn, vr[i], &value[i]);
        if (st != FMU_OK)
            return (fmi2Status)st;
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                       const fmi2Real value[])
{
    static const char fn[] = "fmi2SetReal";
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    if (nvr > 0 && (vr == NULL || value == NULL))
        return fail(inst, fn, "vr or value is NULL");
    /* all checked before any is written: a refused call changes nothing
     * (but a tunable parameter the plant's check refuses, see fmu_put_real) */
    for (size_t i = 0; i < nvr; i++) {
        fmu_status st = fmu_check_real(inst, fn, vr[i], value[i]);
        if (st != FMU_OK)
            return (fmi2Status)st;
    }
    for (size_t i = 0; i < nvr; i++) {
        fmu_status st = fmu_put_real(inst, fn, vr[i], value[i]);
        if (st != FMU_OK)
            return (fmi2Status)st;
    }
    return fmi2OK;
}

/* This FMU has Real variables only: any value reference given to the
 * Integer, Boolean or String functions names no variable of that type. */
static fmi2Status no_variables(fmi2Component c, const char *fn, const fmi2ValueReference vr[],
                               size_t nvr, const char *type)
{
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    if (nvr == 0)
        return fmi2OK;
    if (vr == NULL)
        return fail(inst, fn, "vr is NULL");
    return (fmi2Status)fmu_no_variable(inst, fn, vr[0], type, "Real");
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          fmi2Integer value[])
{
    (void)value;
    return no_variables(c, "fmi2GetInteger", vr, nvr, "Integer");
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          fmi2Boolean value[])
{
    (void)value;
    return no_variables(c, "fmi2GetBoolean", vr, nvr, "Boolean");
}

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                         fmi2String value[])
{
    (void)value;
    return no_variables(c, "fmi2GetString", vr, nvr, "String");
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          const fmi2Integer value[])
{
    (void)value;
    return no_variables(c, "fmi2SetInteger", vr, nvr, "Integer");
}

fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                          const fmi2Boolean value[])
{
    (void)value;
    return no_variables(c, "fmi2SetBoolean", vr, nvr, "Boolean");
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                         const fmi2String value[])
{
    (void)value;
    return no_variables(c, "fmi2SetString", vr, nvr, "String");
}

/* ------------------------------------------------------------------ */
/* FMU states                                                          */
/* ------------------------------------------------------------------ */

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *FMUstate)
{
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return (fmi2Status)fmu_state_get(inst, "fmi2GetFMUstate", FMUstate);
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate FMUstate)
{
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return (fmi2Status)fmu_state_set(inst, "fmi2SetFMUstate", FMUstate);
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *FMUstate)
{
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return (fmi2Status)fmu_state_free(inst, "fmi2FreeFMUstate", FMUstate);
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate FMUstate, size_t *size)
{
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return (fmi2Status)fmu_state_size(inst, "fmi2SerializedFMUstateSize", FMUstate, size);
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate FMUstate,
                                 fmi2Byte serializedState[], size_t size)
{
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return (fmi2Status)fmu_state_serialize(inst, "fmi2SerializeFMUstate", FMUstate,
                                           (unsigned char *)serializedState, size);
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte serializedState[], size_t size,
                                   fmi2FMUstate *FMUstate)
{
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return (fmi2Status)fmu_state_deserialize(inst, "fmi2DeSerializeFMUstate",
                                             (const unsigned char *)serializedState, size,
                                             FMUstate);
}

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
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return (fmi2Status)fmu_unsupported(inst, "fmi2GetDirectionalDerivative",
                                       "the FMU provides no directional derivatives");
}

fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t nvr,
                                       const fmi2Integer order[], const fmi2Real value[])
{
    (void)vr, (void)nvr, (void)order, (void)value;
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return (fmi2Status)fmu_unsupported(inst, "fmi2SetRealInputDerivatives",
                                       "the FMU holds its inputs over a step (it cannot "
                                       "interpolate them)");
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[],
                                        size_t nvr, const fmi2Integer order[], fmi2Real value[])
{
    (void)vr, (void)nvr, (void)order, (void)value;
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return (fmi2Status)fmu_unsupported(inst, "fmi2GetRealOutputDerivatives",
                                       "the FMU provides no output derivatives");
}

/* ------------------------------------------------------------------ */
/* Co-simulation                                                       */
/* ------------------------------------------------------------------ */

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real currentCommunicationPoint,
                      fmi2Real communicationStepSize, fmi2Boolean noSetFMUStatePriorToCurrentPoint)
{
    (void)noSetFMUStatePriorToCurrentPoint; /* a saved state is a full copy: nothing to drop */
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    double reached;
    return (fmi2Status)fmu_do_step(inst, "fmi2DoStep", currentCommunicationPoint,
                                   communicationStepSize, &reached);
}

/* DoStep runs to completion before it returns (never fmi2Pending): there is
 * no step to cancel and no asynchronous status to ask for. */
fmi2Status fmi2CancelStep(fmi2Component c)
{
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return fail(inst, "fmi2CancelStep", "no step is pending (fmi2DoStep never returns fmi2Pending)");
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *value)
{
    (void)value;
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    if (s == fmi2DoStepStatus)
        return fail(inst, "fmi2GetStatus",
                    "fmi2DoStepStatus: no step is pending (fmi2DoStep never returns fmi2Pending)");
    return fail(inst, "fmi2GetStatus", "this status kind is not an fmi2Status");
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *value)
{
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    if (s != fmi2LastSuccessfulTime)
        return fail(inst, "fmi2GetRealStatus", "only fmi2LastSuccessfulTime is a Real status");
    if (value == NULL)
        return fail(inst, "fmi2GetRealStatus", "value is NULL");
    *value = fmu_time(inst); /* after a failed step: the last time with a finite state */
    return fmi2OK;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *value)
{
    (void)s, (void)value;
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return fail(inst, "fmi2GetIntegerStatus", "FMI 2 defines no Integer status");
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *value)
{
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    if (s != fmi2Terminated)
        return fail(inst, "fmi2GetBooleanStatus", "only fmi2Terminated is a Boolean status");
    if (value == NULL)
        return fail(inst, "fmi2GetBooleanStatus", "value is NULL");
    *value = fmi2False; /* the plant never asks to end the simulation */
    return fmi2OK;
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *value)
{
    (void)s, (void)value;
    fmu_instance *inst = instance(c);
    if (inst == NULL)
        return fmi2Error;
    return fail(inst, "fmi2GetStringStatus",
                "fmi2PendingStatus: no step is pending (fmi2DoStep never returns fmi2Pending)");
}
