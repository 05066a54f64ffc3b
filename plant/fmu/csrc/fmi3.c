/*
 * fmi3.c - the FMI 3.0 interface of the plant, for co-simulation.
 *
 * A thin layer over fmu_instance.h, like fmi2.c. The whole FMI 3.0 API is
 * here because an importer (FMPy) looks every function up by name when it
 * loads the library: the model-exchange and scheduled-execution functions,
 * clocks, event mode and configuration mode exist only to refuse, with a
 * log message saying why. What runs: instantiation for co-simulation,
 * initialization, Float64 variables, DoStep, saved FMU states.
 */
#include <stdio.h>
#include <string.h>

#include "fmi3_platform.h"
#include "fmu_instance.h"

/* FMI 3's logger takes plain text (no format) */
static void emit3(const fmu_logger *lg, fmu_status status, const char *category,
                  const char *message)
{
    fmi3LogMessageCallback log_message = (fmi3LogMessageCallback)lg->callback;
    log_message(lg->environment, (fmi3Status)status, category, message);
}

/* the logger of an instantiation; a NULL logMessage is allowed (no messages) */
static void logger_init(fmu_logger *lg, fmi3String instanceName, fmi3Boolean loggingOn,
                        fmi3InstanceEnvironment env, fmi3LogMessageCallback logMessage)
{
    memset(lg, 0, sizeof *lg);
    lg->emit = emit3;
    lg->callback = (void (*)(void))logMessage;
    lg->environment = env;
    lg->logging_on = loggingOn;
    lg->log_events = 1;
    snprintf(lg->name, sizeof lg->name, "%s", instanceName ? instanceName : "");
}

/* the refusal of a function of another interface type, or unsupported */
static fmi3Status unsupported(fmi3Instance instance, const char *fn, const char *why)
{
    return (fmi3Status)fmu_unsupported(instance, fn, why);
}

#define CS_ONLY "a model-exchange function; this FMU is for co-simulation only"
#define NO_SE "a scheduled-execution function; this FMU is for co-simulation only"
#define NO_EVENTS "the FMU has no event mode (hasEventMode is false): it steps in step mode only"

/* ------------------------------------------------------------------ */
/* Common functions                                                    */
/* ------------------------------------------------------------------ */

const char *fmi3GetVersion(void)
{
    return FMI3_VERSION;
}

fmi3Status fmi3SetDebugLogging(fmi3Instance instance, fmi3Boolean loggingOn, size_t nCategories,
                               const fmi3String categories[])
{
    return (fmi3Status)fmu_set_debug_logging(instance, "fmi3SetDebugLogging", loggingOn,
                                             nCategories, categories);
}

fmi3Instance fmi3InstantiateModelExchange(fmi3String instanceName, fmi3String instantiationToken,
                                          fmi3String resourcePath, fmi3Boolean visible,
                                          fmi3Boolean loggingOn,
                                          fmi3InstanceEnvironment instanceEnvironment,
                                          fmi3LogMessageCallback logMessage)
{
    (void)instantiationToken, (void)resourcePath, (void)visible;
    fmu_logger lg;
    logger_init(&lg, instanceName, loggingOn, instanceEnvironment, logMessage);
    fmu_log(&lg, FMU_ERROR, "fmi3InstantiateModelExchange",
            "refused: this FMU is for co-simulation only (fmi3InstantiateCoSimulation)");
    return NULL;
}

fmi3Instance fmi3InstantiateCoSimulation(
    fmi3String instanceName, fmi3String instantiationToken, fmi3String resourcePath,
    fmi3Boolean visible, fmi3Boolean loggingOn, fmi3Boolean eventModeUsed,
    fmi3Boolean earlyReturnAllowed, const fmi3ValueReference requiredIntermediateVariables[],
    size_t nRequiredIntermediateVariables, fmi3InstanceEnvironment instanceEnvironment,
    fmi3LogMessageCallback logMessage, fmi3IntermediateUpdateCallback intermediateUpdate)
{
    static const char fn[] = "fmi3InstantiateCoSimulation";
    (void)resourcePath;       /* the FMU needs no resources: all is compiled in */
    (void)visible;            /* no user interface */
    (void)earlyReturnAllowed; /* a step always runs to its end */
    (void)requiredIntermediateVariables;
    (void)intermediateUpdate; /* never called: no intermediate updates */
    fmu_logger lg;
    logger_init(&lg, instanceName, loggingOn, instanceEnvironment, logMessage);
    if (instanceName == NULL || instanceName[0] == '\0') {
        fmu_log(&lg, FMU_ERROR, fn, "instanceName is empty");
        return NULL;
    }
    if (eventModeUsed) {
        fmu_log(&lg, FMU_ERROR, fn, "eventModeUsed refused: %s", NO_EVENTS);
        return NULL;
    }
    if (nRequiredIntermediateVariables > 0) {
        fmu_log(&lg, FMU_ERROR, fn,
                "requiredIntermediateVariables refused: the FMU provides no intermediate updates");
        return NULL;
    }
    return fmu_instance_new(&lg, fn, "instantiationToken", instantiationToken);
}

fmi3Instance fmi3InstantiateScheduledExecution(
    fmi3String instanceName, fmi3String instantiationToken, fmi3String resourcePath,
    fmi3Boolean visible, fmi3Boolean loggingOn, fmi3InstanceEnvironment instanceEnvironment,
    fmi3LogMessageCallback logMessage, fmi3ClockUpdateCallback clockUpdate,
    fmi3LockPreemptionCallback lockPreemption, fmi3UnlockPreemptionCallback unlockPreemption)
{
    (void)instantiationToken, (void)resourcePath, (void)visible, (void)clockUpdate,
        (void)lockPreemption, (void)unlockPreemption;
    fmu_logger lg;
    logger_init(&lg, instanceName, loggingOn, instanceEnvironment, logMessage);
    fmu_log(&lg, FMU_ERROR, "fmi3InstantiateScheduledExecution",
            "refused: this FMU is for co-simulation only (fmi3InstantiateCoSimulation)");
    return NULL;
}

void fmi3FreeInstance(fmi3Instance instance)
{
    fmu_instance_free(instance);
}

fmi3Status fmi3EnterInitializationMode(fmi3Instance instance, fmi3Boolean toleranceDefined,
                                       fmi3Float64 tolerance, fmi3Float64 startTime,
                                       fmi3Boolean stopTimeDefined, fmi3Float64 stopTime)
{
    static const char fn[] = "fmi3EnterInitializationMode";
    (void)toleranceDefined; /* fixed-step explicit Euler: no tolerance to meet */
    (void)tolerance;
    fmu_status st = fmu_setup_experiment(instance, fn, startTime, stopTimeDefined, stopTime);
    if (st != FMU_OK)
        return (fmi3Status)st;
    return (fmi3Status)fmu_enter_initialization(instance, fn);
}

fmi3Status fmi3ExitInitializationMode(fmi3Instance instance)
{
    return (fmi3Status)fmu_exit_initialization(instance, "fmi3ExitInitializationMode");
}

fmi3Status fmi3EnterEventMode(fmi3Instance instance)
{
    return unsupported(instance, "fmi3EnterEventMode", NO_EVENTS);
}

fmi3Status fmi3Terminate(fmi3Instance instance)
{
    return (fmi3Status)fmu_terminate(instance, "fmi3Terminate");
}

fmi3Status fmi3Reset(fmi3Instance instance)
{
    return (fmi3Status)fmu_reset(instance, "fmi3Reset");
}

/* ------------------------------------------------------------------ */
/* Getting and setting variables                                       */
/* ------------------------------------------------------------------ */

/* every variable is a scalar: as many values as value references */
static fmi3Status shape_ok(fmi3Instance instance, const char *fn, const void *vrs, size_t nvr,
                           const void *values, size_t n_values)
{
    if (!fmu_instance_ok(instance))
        return fmi3Error;
    if (n_values != nvr) {
        fmu_instance *inst = instance;
        fmu_log(&inst->logger, FMU_ERROR, fn,
                "nValues = %zu is not nValueReferences = %zu (every variable is a scalar)",
                n_values, nvr);
        return fmi3Error;
    }
    if (nvr > 0 && (vrs == NULL || values == NULL))
        return (fmi3Status)fmu_error(instance, fn, "valueReferences or values is NULL");
    return fmi3OK;
}

fmi3Status fmi3GetFloat64(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                          size_t nValueReferences, fmi3Float64 values[], size_t nValues)
{
    static const char fn[] = "fmi3GetFloat64";
    if (shape_ok(instance, fn, valueReferences, nValueReferences, values, nValues) != fmi3OK)
        return fmi3Error;
    return (fmi3Status)fmu_get_reals(instance, fn, valueReferences, nValueReferences, values);
}

fmi3Status fmi3SetFloat64(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                          size_t nValueReferences, const fmi3Float64 values[], size_t nValues)
{
    static const char fn[] = "fmi3SetFloat64";
    if (shape_ok(instance, fn, valueReferences, nValueReferences, values, nValues) != fmi3OK)
        return fmi3Error;
    return (fmi3Status)fmu_set_reals(instance, fn, valueReferences, nValueReferences, values);
}

/* This FMU has Float64 variables only: a value reference given to any
 * other type's function names no variable of that type. */
static fmi3Status no_variables(fmi3Instance instance, const char *fn,
                               const fmi3ValueReference vrs[], size_t nvr, const char *type)
{
    return (fmi3Status)fmu_no_variables(instance, fn, vrs, nvr, "valueReferences", type,
                                        "Float64");
}

#define NO_VARIABLES(Type, CType)                                                              \
    fmi3Status fmi3Get##Type(fmi3Instance instance, const fmi3ValueReference valueReferences[], \
                             size_t nValueReferences, CType values[], size_t nValues)          \
    {                                                                                          \
        (void)values, (void)nValues;                                                           \
        return no_variables(instance, "fmi3Get" #Type, valueReferences, nValueReferences,      \
                            #Type);                                                            \
    }                                                                                          \
    fmi3Status fmi3Set##Type(fmi3Instance instance, const fmi3ValueReference valueReferences[], \
                             size_t nValueReferences, const CType values[], size_t nValues)    \
    {                                                                                          \
        (void)values, (void)nValues;                                                           \
        return no_variables(instance, "fmi3Set" #Type, valueReferences, nValueReferences,      \
                            #Type);                                                            \
    }

NO_VARIABLES(Float32, fmi3Float32)
NO_VARIABLES(Int8, fmi3Int8)
NO_VARIABLES(UInt8, fmi3UInt8)
NO_VARIABLES(Int16, fmi3Int16)
NO_VARIABLES(UInt16, fmi3UInt16)
NO_VARIABLES(Int32, fmi3Int32)
NO_VARIABLES(UInt32, fmi3UInt32)
NO_VARIABLES(Int64, fmi3Int64)
NO_VARIABLES(UInt64, fmi3UInt64)
NO_VARIABLES(Boolean, fmi3Boolean)
NO_VARIABLES(String, fmi3String)

fmi3Status fmi3GetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                         size_t nValueReferences, size_t valueSizes[], fmi3Binary values[],
                         size_t nValues)
{
    (void)valueSizes, (void)values, (void)nValues;
    return no_variables(instance, "fmi3GetBinary", valueReferences, nValueReferences, "Binary");
}

fmi3Status fmi3SetBinary(fmi3Instance instance, const fmi3ValueReference valueReferences[],
                         size_t nValueReferences, const size_t valueSizes[],
                         const fmi3Binary values[], size_t nValues)
{
    (void)valueSizes, (void)values, (void)nValues;
    return no_variables(instance, "fmi3SetBinary", valueReferences, nValueReferences, "Binary");
}

/* ------------------------------------------------------------------ */
/* Clocks: the FMU has none                                            */
/* ------------------------------------------------------------------ */

/* the clock functions with one array, or two of one type, beside the value references */
#define NO_CLOCKS(Name, Element)                                                              \
    fmi3Status fmi3##Name(fmi3Instance instance, const fmi3ValueReference valueReferences[], \
                          size_t nValueReferences, Element values[])                         \
    {                                                                                        \
        (void)values;                                                                        \
        return no_variables(instance, "fmi3" #Name, valueReferences, nValueReferences,       \
                            "Clock");                                                        \
    }
#define NO_CLOCKS_FRACTION(Name, Element)                                                     \
    fmi3Status fmi3##Name(fmi3Instance instance, const fmi3ValueReference valueReferences[], \
                          size_t nValueReferences, Element counters[],                       \
                          Element resolutions[])                                             \
    {                                                                                        \
        (void)counters, (void)resolutions;                                                   \
        return no_variables(instance, "fmi3" #Name, valueReferences, nValueReferences,       \
                            "Clock");                                                        \
    }

NO_CLOCKS(GetClock, fmi3Clock)
NO_CLOCKS(SetClock, const fmi3Clock)
NO_CLOCKS(GetShiftDecimal, fmi3Float64)
NO_CLOCKS(SetIntervalDecimal, const fmi3Float64)
NO_CLOCKS(SetShiftDecimal, const fmi3Float64)
NO_CLOCKS_FRACTION(GetShiftFraction, fmi3UInt64)
NO_CLOCKS_FRACTION(SetIntervalFraction, const fmi3UInt64)
NO_CLOCKS_FRACTION(SetShiftFraction, const fmi3UInt64)

fmi3Status fmi3GetIntervalDecimal(fmi3Instance instance,
                                  const fmi3ValueReference valueReferences[],
                                  size_t nValueReferences, fmi3Float64 intervals[],
                                  fmi3IntervalQualifier qualifiers[])
{
    (void)intervals, (void)qualifiers;
    return no_variables(instance, "fmi3GetIntervalDecimal", valueReferences, nValueReferences,
                        "Clock");
}

fmi3Status fmi3GetIntervalFraction(fmi3Instance instance,
                                   const fmi3ValueReference valueReferences[],
                                   size_t nValueReferences, fmi3UInt64 counters[],
                                   fmi3UInt64 resolutions[], fmi3IntervalQualifier qualifiers[])
{
    (void)counters, (void)resolutions, (void)qualifiers;
    return no_variables(instance, "fmi3GetIntervalFraction", valueReferences, nValueReferences,
                        "Clock");
}

/* ------------------------------------------------------------------ */
/* Dependencies, derivatives, configuration mode                       */
/* ------------------------------------------------------------------ */

fmi3Status fmi3GetNumberOfVariableDependencies(fmi3Instance instance,
                                               fmi3ValueReference valueReference,
                                               size_t *nDependencies)
{
    (void)valueReference, (void)nDependencies;
    return unsupported(instance, "fmi3GetNumberOfVariableDependencies",
                       "the FMU provides no per-element dependencies");
}

fmi3Status fmi3GetVariableDependencies(fmi3Instance instance, fmi3ValueReference dependent,
                                       size_t elementIndicesOfDependent[],
                                       fmi3ValueReference independents[],
                                       size_t elementIndicesOfIndependents[],
                                       fmi3DependencyKind dependencyKinds[], size_t nDependencies)
{
    (void)dependent, (void)elementIndicesOfDependent, (void)independents,
        (void)elementIndicesOfIndependents, (void)dependencyKinds, (void)nDependencies;
    return unsupported(instance, "fmi3GetVariableDependencies",
                       "the FMU provides no per-element dependencies");
}

/* the directional and the adjoint derivatives: the same arguments, neither provided */
#define NO_DERIVATIVES(Name, kind)                                                           \
    fmi3Status fmi3##Name(fmi3Instance instance, const fmi3ValueReference unknowns[],      \
                          size_t nUnknowns, const fmi3ValueReference knowns[],             \
                          size_t nKnowns, const fmi3Float64 seed[], size_t nSeed,          \
                          fmi3Float64 sensitivity[], size_t nSensitivity)                  \
    {                                                                                      \
        (void)unknowns, (void)nUnknowns, (void)knowns, (void)nKnowns, (void)seed,          \
            (void)nSeed, (void)sensitivity, (void)nSensitivity;                            \
        return unsupported(instance, "fmi3" #Name, "the FMU provides no " kind " derivatives"); \
    }

NO_DERIVATIVES(GetDirectionalDerivative, "directional")
NO_DERIVATIVES(GetAdjointDerivative, "adjoint")

fmi3Status fmi3EnterConfigurationMode(fmi3Instance instance)
{
    return unsupported(instance, "fmi3EnterConfigurationMode",
                       "the FMU has no structural parameters");
}

fmi3Status fmi3ExitConfigurationMode(fmi3Instance instance)
{
    return unsupported(instance, "fmi3ExitConfigurationMode",
                       "the FMU has no structural parameters");
}

fmi3Status fmi3EvaluateDiscreteStates(fmi3Instance instance)
{
    return unsupported(instance, "fmi3EvaluateDiscreteStates", NO_EVENTS);
}

fmi3Status fmi3UpdateDiscreteStates(fmi3Instance instance, fmi3Boolean *discreteStatesNeedUpdate,
                                    fmi3Boolean *terminateSimulation,
                                    fmi3Boolean *nominalsOfContinuousStatesChanged,
                                    fmi3Boolean *valuesOfContinuousStatesChanged,
                                    fmi3Boolean *nextEventTimeDefined, fmi3Float64 *nextEventTime)
{
    (void)discreteStatesNeedUpdate, (void)terminateSimulation,
        (void)nominalsOfContinuousStatesChanged, (void)valuesOfContinuousStatesChanged,
        (void)nextEventTimeDefined, (void)nextEventTime;
    return unsupported(instance, "fmi3UpdateDiscreteStates", NO_EVENTS);
}

/* ------------------------------------------------------------------ */
/* FMU states                                                          */
/* ------------------------------------------------------------------ */

FMU_STATE_FUNCTIONS(fmi3Status, fmi3Instance, fmi3FMUState, fmi3Byte, fmi3GetFMUState,
                    fmi3SetFMUState, fmi3FreeFMUState, fmi3SerializedFMUStateSize,
                    fmi3SerializeFMUState, fmi3DeserializeFMUState)

/* ------------------------------------------------------------------ */
/* Model exchange: refused                                             */
/* ------------------------------------------------------------------ */

fmi3Status fmi3EnterContinuousTimeMode(fmi3Instance instance)
{
    return unsupported(instance, "fmi3EnterContinuousTimeMode", CS_ONLY);
}

fmi3Status fmi3CompletedIntegratorStep(fmi3Instance instance,
                                       fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                                       fmi3Boolean *enterEventMode,
                                       fmi3Boolean *terminateSimulation)
{
    (void)noSetFMUStatePriorToCurrentPoint, (void)enterEventMode, (void)terminateSimulation;
    return unsupported(instance, "fmi3CompletedIntegratorStep", CS_ONLY);
}

fmi3Status fmi3SetTime(fmi3Instance instance, fmi3Float64 time)
{
    (void)time;
    return unsupported(instance, "fmi3SetTime", CS_ONLY);
}

/* the model-exchange functions that take an array of Float64 and its length */
#define CS_ONLY_ARRAY(Name, Element)                                                  \
    fmi3Status fmi3##Name(fmi3Instance instance, Element values[], size_t nValues) \
    {                                                                               \
        (void)values, (void)nValues;                                                \
        return unsupported(instance, "fmi3" #Name, CS_ONLY);                        \
    }

CS_ONLY_ARRAY(SetContinuousStates, const fmi3Float64)
CS_ONLY_ARRAY(GetContinuousStateDerivatives, fmi3Float64)
CS_ONLY_ARRAY(GetEventIndicators, fmi3Float64)
CS_ONLY_ARRAY(GetContinuousStates, fmi3Float64)
CS_ONLY_ARRAY(GetNominalsOfContinuousStates, fmi3Float64)

fmi3Status fmi3GetNumberOfEventIndicators(fmi3Instance instance, size_t *nEventIndicators)
{
    (void)nEventIndicators;
    return unsupported(instance, "fmi3GetNumberOfEventIndicators", CS_ONLY);
}

fmi3Status fmi3GetNumberOfContinuousStates(fmi3Instance instance, size_t *nContinuousStates)
{
    (void)nContinuousStates;
    return unsupported(instance, "fmi3GetNumberOfContinuousStates", CS_ONLY);
}

/* ------------------------------------------------------------------ */
/* Co-simulation                                                       */
/* ------------------------------------------------------------------ */

fmi3Status fmi3EnterStepMode(fmi3Instance instance)
{
    return unsupported(instance, "fmi3EnterStepMode",
                       "the FMU is in step mode from ExitInitializationMode on (it has no event "
                       "mode to leave)");
}

fmi3Status fmi3GetOutputDerivatives(fmi3Instance instance,
                                    const fmi3ValueReference valueReferences[],
                                    size_t nValueReferences, const fmi3Int32 orders[],
                                    fmi3Float64 values[], size_t nValues)
{
    (void)valueReferences, (void)orders, (void)values, (void)nValues;
    if (nValueReferences == 0 && fmu_instance_ok(instance))
        return fmi3OK;
    return (fmi3Status)fmu_unsupported(instance, "fmi3GetOutputDerivatives",
                                       "the FMU provides no output derivatives "
                                       "(maxOutputDerivativeOrder is 0)");
}

fmi3Status fmi3DoStep(fmi3Instance instance, fmi3Float64 currentCommunicationPoint,
                      fmi3Float64 communicationStepSize,
                      fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                      fmi3Boolean *eventHandlingNeeded, fmi3Boolean *terminateSimulation,
                      fmi3Boolean *earlyReturn, fmi3Float64 *lastSuccessfulTime)
{
    (void)noSetFMUStatePriorToCurrentPoint; /* a saved state is a full copy: nothing to drop */
    if (!fmu_instance_ok(instance))
        return fmi3Error;
    /* no events, no reason to stop, a step always runs to its end */
    if (eventHandlingNeeded != NULL)
        *eventHandlingNeeded = fmi3False;
    if (terminateSimulation != NULL)
        *terminateSimulation = fmi3False;
    if (earlyReturn != NULL)
        *earlyReturn = fmi3False;
    double reached;
    fmu_status st = fmu_do_step(instance, "fmi3DoStep", currentCommunicationPoint,
                                communicationStepSize, &reached);
    if (lastSuccessfulTime != NULL)
        *lastSuccessfulTime = reached;
    return (fmi3Status)st;
}

/* ------------------------------------------------------------------ */
/* Scheduled execution: refused                                        */
/* ------------------------------------------------------------------ */

fmi3Status fmi3ActivateModelPartition(fmi3Instance instance, fmi3ValueReference clockReference,
                                      fmi3Float64 activationTime)
{
    (void)clockReference, (void)activationTime;
    return unsupported(instance, "fmi3ActivateModelPartition", NO_SE);
}
