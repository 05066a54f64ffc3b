/*
 * fmu_instance.h - one FMU instance of the plant, whatever the FMI version.
 *
 * fmi2.c and fmi3.c are thin: they check their arguments' shapes, turn their
 * types into these and call the functions here, which hold the behaviour
 * both versions share (the modes, the variables, the step, the saved
 * states). An instance owns one dct_plant, the initial conditions it
 * starts from, its time and mode and its logger; nothing is global, so any
 * number of instances run side by side in one process.
 *
 * Every function that can fail logs one line "<FMI function>: <cause>"
 * through the instance's logger and returns FMU_ERROR; `fn` is the FMI
 * function's name for that line. Every function that returns an fmu_status
 * checks its instance first: a handle that is not a live instance (NULL,
 * freed, foreign) is FMU_ERROR without a message, there being no logger to
 * tell it with; so fmi2.c and fmi3.c pass the importer's handle on as it is.
 */
#ifndef FMU_INSTANCE_H
#define FMU_INSTANCE_H

#include <stddef.h>
#include <stdint.h>

#include "dct_plant.h"
#include "fmu_model.h"

/* the values of fmi2Status and fmi3Status (the same numbers in both) */
typedef enum {
    FMU_OK = 0,
    FMU_WARNING = 1,
    FMU_DISCARD = 2,
    FMU_ERROR = 3,
    FMU_FATAL = 4
} fmu_status;

/* The instance's mode (FMI 2 and FMI 3 co-simulation states). */
typedef enum {
    FMU_MODE_INSTANTIATED = 0,   /* parameters, initial conditions and inputs may be set */
    FMU_MODE_INITIALIZATION = 1, /* the same, until ExitInitializationMode */
    FMU_MODE_STEP = 2,           /* DoStep; inputs and tunable parameters may be set */
    FMU_MODE_TERMINATED = 3,     /* only getters, Reset, Free */
    FMU_MODE_ERROR = 4           /* after a failed step or initialization: getters,
                                    Reset, Free, or a saved FMU state set back */
} fmu_mode;

#define FMU_N_INPUTS (sizeof(dct_inputs) / sizeof(double))
#define FMU_NAME_MAX 128         /* instance names longer than this are cut in messages */
#define FMU_MESSAGE_MAX 1024     /* one log line, longer is cut */

/* The log categories of modelDescription.xml. Errors and warnings are always
 * logged; info (initialization done, ...) as logEvents only when logging is on. */
#define FMU_LOG_WARNING "logStatusWarning"
#define FMU_LOG_ERROR "logStatusError"
#define FMU_LOG_EVENTS "logEvents"

/* How messages reach the importer: `emit` is the FMI version's (fmi2.c's
 * calls the printf-like fmi2CallbackLogger, fmi3.c's the plain
 * fmi3LogMessageCallback), `callback` the importer's function, cast back by
 * emit. A NULL callback: no messages. */
typedef struct fmu_logger fmu_logger;
typedef void fmu_emit_fn(const fmu_logger *logger, fmu_status status, const char *category,
                         const char *message);
struct fmu_logger {
    fmu_emit_fn *emit;
    void (*callback)(void);
    void *environment;            /* fmi2ComponentEnvironment / fmi3InstanceEnvironment */
    int logging_on;               /* SetDebugLogging / loggingOn */
    int log_events;               /* the logEvents category on (all are, unless named) */
    char name[FMU_NAME_MAX];
};

/* Everything that decides the instance's future: a saved FMU state is a copy
 * of it, byte for byte (no pointers in it, so it serializes as it is). */
typedef struct {
    dct_plant plant;              /* params: the FMU's parameters as set; inputs as set */
    dct_initial initial;          /* the state ExitInitializationMode resets the plant to */
    double base_time_s;           /* time = base_time_s + steps * step: counted, not summed */
    int64_t steps;                /* plant steps since base_time_s that ended finite */
    double stop_time_s;
    int stop_time_defined;
    int mode;                     /* fmu_mode */
    unsigned char input_set[FMU_N_INPUTS]; /* 1: set before initialization ended (written
                                              after the reset of ExitInitializationMode) */
} fmu_core;

typedef struct {
    uint32_t magic;               /* FMU_INSTANCE_MAGIC while alive: a stale pointer is refused */
    fmu_logger logger;
    fmu_core core;
} fmu_instance;

/* a saved FMU state (fmi2FMUstate / fmi3FMUState) */
typedef struct {
    uint32_t magic;
    fmu_core core;
} fmu_saved;

/* Logging without an instance (a refused instantiation) and with one.
 * status FMU_OK is info: logged only when logging and logEvents are on. */
#if defined(__GNUC__)
#define FMU_PRINTF(f, a) __attribute__((format(printf, f, a)))
#else
#define FMU_PRINTF(f, a)
#endif
void fmu_log(const fmu_logger *logger, fmu_status status, const char *fn, const char *fmt, ...)
    FMU_PRINTF(4, 5);

/* NULL (logged) when the token is not fmu_token or the table is inconsistent;
 * else a new instance in FMU_MODE_INSTANTIATED with the default inputs and
 * outputs readable. token_name: what the FMI version calls it (GUID,
 * instantiationToken), for the message. */
fmu_instance *fmu_instance_new(const fmu_logger *logger, const char *fn, const char *token_name,
                               const char *token);
void fmu_instance_free(fmu_instance *inst);
/* 1: inst is a live instance (not NULL, not freed) */
int fmu_instance_ok(const fmu_instance *inst);

fmu_status fmu_set_debug_logging(fmu_instance *inst, const char *fn, int logging_on,
                                 size_t n_categories, const char *const categories[]);

/* start time (and stop time, refusing steps beyond it); FMU_MODE_INSTANTIATED only */
fmu_status fmu_setup_experiment(fmu_instance *inst, const char *fn, double start_time,
                                int stop_time_defined, double stop_time);
fmu_status fmu_enter_initialization(fmu_instance *inst, const char *fn);
/* dct_plant_init (the parameters checked), dct_plant_reset(initial), then the
 * inputs set so far written (not applied: the outputs are the reset's) */
fmu_status fmu_exit_initialization(fmu_instance *inst, const char *fn);
fmu_status fmu_terminate(fmu_instance *inst, const char *fn);
/* back to the instantiated state: fmu_params, fmu_initial, default inputs */
fmu_status fmu_reset(fmu_instance *inst, const char *fn);

/* the instance's time: start time + steps * the plant's step (inst live) */
double fmu_time(const fmu_instance *inst);

/* Float64 (FMI 2 Real) variables, nvr of them (the caller has checked that
 * vrs and values are there). Setting checks every value (mode, kind,
 * finite, range) before it writes any: a refused call changes nothing, but
 * for a tunable parameter set while stepping that the plant's check
 * (dct_plant_prepare) refuses, which keeps its old value. */
fmu_status fmu_get_reals(fmu_instance *inst, const char *fn, const uint32_t vrs[], size_t nvr,
                         double values[]);
fmu_status fmu_set_reals(fmu_instance *inst, const char *fn, const uint32_t vrs[], size_t nvr,
                         const double values[]);

/* The getter or setter of a type that has no variables (every type but
 * Real / Float64): FMU_OK for none, else an error naming the first value
 * reference. vrs_name: what the FMI version calls vrs, for the message. */
fmu_status fmu_no_variables(fmu_instance *inst, const char *fn, const uint32_t vrs[], size_t nvr,
                            const char *vrs_name, const char *type, const char *real_type);

/* n = round(h / step) plant steps from t (which must be the instance's time);
 * h a positive whole multiple of the plant's step. *reached: the time after
 * the last step that ended with a finite state. A plant error puts the
 * instance in FMU_MODE_ERROR. */
fmu_status fmu_do_step(fmu_instance *inst, const char *fn, double t, double h, double *reached);

/* Saved FMU states (copies of fmu_core). get: *state NULL -> a new one,
 * else that one overwritten. */
fmu_status fmu_state_get(fmu_instance *inst, const char *fn, void **state);
fmu_status fmu_state_set(fmu_instance *inst, const char *fn, const void *state);
fmu_status fmu_state_free(fmu_instance *inst, const char *fn, void **state);
fmu_status fmu_state_size(fmu_instance *inst, const char *fn, const void *state, size_t *size);
/* a byte array: header (magic, format version, byte order, sizeof(dct_plant),
 * sizeof(fmu_core), the token), the copy, a checksum */
fmu_status fmu_state_serialize(fmu_instance *inst, const char *fn, const void *state,
                               unsigned char *buf, size_t size);
/* refused (naming what does not match) unless written by this FMU, same
 * token, same layout, undamaged; *state NULL -> a new one, else overwritten */
fmu_status fmu_state_deserialize(fmu_instance *inst, const char *fn, const unsigned char *buf,
                                 size_t size, void **state);

/* The six FMI functions of saved FMU states, which FMI 2 and FMI 3 have
 * with the same arguments under names and types of their own: fmi2.c and
 * fmi3.c each define theirs with this, every one the call of its
 * fmu_state_* with the function's name. */
#define FMU_STATE_FUNCTIONS(Status, Instance, State, Byte, Get, Set, Free, Size, Serialize,    \
                            Deserialize)                                                     \
    Status Get(Instance instance, State *state)                                              \
    {                                                                                        \
        return (Status)fmu_state_get(instance, #Get, state);                                 \
    }                                                                                        \
    Status Set(Instance instance, State state)                                               \
    {                                                                                        \
        return (Status)fmu_state_set(instance, #Set, state);                                 \
    }                                                                                        \
    Status Free(Instance instance, State *state)                                             \
    {                                                                                        \
        return (Status)fmu_state_free(instance, #Free, state);                               \
    }                                                                                        \
    Status Size(Instance instance, State state, size_t *size)                                \
    {                                                                                        \
        return (Status)fmu_state_size(instance, #Size, state, size);                         \
    }                                                                                        \
    Status Serialize(Instance instance, State state, Byte serialized[], size_t size)         \
    {                                                                                        \
        return (Status)fmu_state_serialize(instance, #Serialize, state,                      \
                                           (unsigned char *)serialized, size);               \
    }                                                                                        \
    Status Deserialize(Instance instance, const Byte serialized[], size_t size, State *state) \
    {                                                                                        \
        return (Status)fmu_state_deserialize(instance, #Deserialize,                         \
                                             (const unsigned char *)serialized, size, state); \
    }

/* an error for a function this FMU does not support, with why */
fmu_status fmu_unsupported(fmu_instance *inst, const char *fn, const char *why);
/* an error saying what */
fmu_status fmu_error(fmu_instance *inst, const char *fn, const char *what);
/* an error for a call the present mode does not allow (what: the call's purpose) */
fmu_status fmu_not_in_mode(fmu_instance *inst, const char *fn);

#endif
