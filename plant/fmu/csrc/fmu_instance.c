/*
 * fmu_instance.c - the FMU instance shared by FMI 2 (fmi2.c) and FMI 3
 * (fmi3.c): modes, variables, steps and saved states over the plant's C API.
 *
 * The run is the one plant/simulate.py makes, bit for bit: the plant is
 * initialised with the FMU's parameters (default inputs), reset to the
 * initial conditions, the inputs given before initialization are written
 * (not applied: the outputs at the start time are the reset's), and each
 * DoStep is one dct_plant_step of n plant steps.
 */
#include "fmu_instance.h"

#include <limits.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define FMU_INSTANCE_MAGIC 0x464d5549u /* "FMUI" */
#define FMU_SAVED_MAGIC 0x464d5553u    /* "FMUS" */

/* a communication step is a whole number of plant steps within this
 * relative tolerance: an importer's step is often a difference of two
 * times, off by a few ulps */
#define FMU_STEP_RTOL 1e-9

/* how many changed parameters the "parameter check failed" message names */
#define FMU_CHANGED_NAMED 6

/* ------------------------------------------------------------------ */
/* Logging                                                             */
/* ------------------------------------------------------------------ */

static void log_v(const fmu_logger *lg, fmu_status status, const char *fn, const char *fmt,
                  va_list ap)
{
    if (lg == NULL || lg->emit == NULL || lg->callback == NULL)
        return;
    const char *category;
    if (status == FMU_OK) {
        if (!lg->logging_on || !lg->log_events)
            return;
        category = FMU_LOG_EVENTS;
    } else if (status == FMU_WARNING) {
        category = FMU_LOG_WARNING;
    } else {
        category = FMU_LOG_ERROR;
    }
    char msg[FMU_MESSAGE_MAX];
    int k = snprintf(msg, sizeof msg, "%s: ", fn);
    if (k < 0)
        k = 0;
    if ((size_t)k >= sizeof msg)
        k = (int)sizeof msg - 1;
    vsnprintf(msg + k, sizeof msg - (size_t)k, fmt, ap);
    /* one line: a name or token from the importer may hold a line break */
    for (char *p = msg; *p; p++)
        if ((unsigned char)*p < 0x20)
            *p = ' ';
    lg->emit(lg, status, category, msg);
}

void fmu_log(const fmu_logger *logger, fmu_status status, const char *fn, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    log_v(logger, status, fn, fmt, ap);
    va_end(ap);
}

/* logs an error, returns FMU_ERROR */
static fmu_status fail(const fmu_instance *inst, const char *fn, const char *fmt, ...)
    FMU_PRINTF(3, 4);
static fmu_status fail(const fmu_instance *inst, const char *fn, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    log_v(&inst->logger, FMU_ERROR, fn, fmt, ap);
    va_end(ap);
    return FMU_ERROR;
}

/* ------------------------------------------------------------------ */
/* The variables table                                                 */
/* ------------------------------------------------------------------ */

/* The table is generated, so a mistake in it would read or write the wrong
 * memory silently: each offset is checked against its struct once per
 * instantiation (a few hundred comparisons). */
static int table_ok(const fmu_logger *lg, const char *fn)
{
    const size_t in0 = offsetof(dct_plant, inputs);
    const size_t out0 = offsetof(dct_plant, outputs);
    const size_t par0 = offsetof(dct_plant, params);
    const size_t flt0 = offsetof(dct_plant, faults);
    if (fmu_n_vars < 1 || fmu_vars[0].kind != FMU_VAR_TIME) {
        fmu_log(lg, FMU_ERROR, fn, "fmu_variables.c: value reference 0 is not the time");
        return 0;
    }
    for (unsigned int i = 0; i < fmu_n_vars; i++) {
        const fmu_var *v = &fmu_vars[i];
        size_t lo = 0, size = 0;
        switch (v->kind) {
        case FMU_VAR_TIME:
            if (i != 0) {
                fmu_log(lg, FMU_ERROR, fn, "fmu_variables.c: a second time variable at %u", i);
                return 0;
            }
            continue;
        case FMU_VAR_INPUT:
            lo = in0;
            size = sizeof(dct_inputs);
            break;
        case FMU_VAR_OUTPUT:
            lo = out0;
            size = sizeof(dct_outputs);
            break;
        case FMU_VAR_PARAM_FIXED:
        case FMU_VAR_PARAM_TUNABLE:
            /* the car's parameters, or the physical faults (tunable too:
             * dct_plant_prepare checks and applies both) */
            if (v->offset >= flt0 && v->offset < flt0 + sizeof(dct_faults)) {
                lo = flt0;
                size = sizeof(dct_faults);
            } else {
                lo = par0;
                size = sizeof(dct_params);
            }
            break;
        case FMU_VAR_INITIAL:
            lo = 0;
            size = sizeof(dct_initial);
            break;
        default:
            fmu_log(lg, FMU_ERROR, fn, "fmu_variables.c: variable %u has unknown kind %d", i,
                    v->kind);
            return 0;
        }
        const char *name = v->name ? v->name : "(unnamed)";
        if (v->offset < lo || v->offset + sizeof(double) > lo + size ||
            (v->kind == FMU_VAR_INPUT && (v->offset - lo) % sizeof(double) != 0)) {
            fmu_log(lg, FMU_ERROR, fn,
                    "fmu_variables.c: variable %u (%s) has offset %zu outside its struct", i,
                    name, v->offset);
            return 0;
        }
        if (v->name == NULL || !(v->min <= v->max)) {
            fmu_log(lg, FMU_ERROR, fn, "fmu_variables.c: variable %u (%s) has no name or bad bounds",
                    i, name);
            return 0;
        }
    }
    return 1;
}

static double *var_ptr(fmu_core *c, const fmu_var *v)
{
    if (v->kind == FMU_VAR_INITIAL)
        return (double *)((char *)&c->initial + v->offset);
    return (double *)((char *)&c->plant + v->offset);
}

static size_t input_index(const fmu_var *v)
{
    return (v->offset - offsetof(dct_plant, inputs)) / sizeof(double);
}

static const char *kind_word(int kind)
{
    switch (kind) {
    case FMU_VAR_TIME:
        return "the time";
    case FMU_VAR_INPUT:
        return "input";
    case FMU_VAR_OUTPUT:
        return "output";
    case FMU_VAR_PARAM_FIXED:
        return "fixed parameter";
    case FMU_VAR_PARAM_TUNABLE:
        return "tunable parameter";
    case FMU_VAR_INITIAL:
        return "initial condition";
    }
    return "variable";
}

/* ------------------------------------------------------------------ */
/* Instances                                                           */
/* ------------------------------------------------------------------ */

/* The instantiated state: the FMU's parameters, the default initial
 * conditions, dct_plant_init's inputs and outputs (readable at once). */
static int core_init(fmu_core *c)
{
    memset(c, 0, sizeof *c);
    memcpy(&c->plant.params, &fmu_params, sizeof fmu_params);
    memcpy(&c->initial, &fmu_initial, sizeof fmu_initial);
    c->mode = FMU_MODE_INSTANTIATED;
    return dct_plant_init(&c->plant);
}

fmu_instance *fmu_instance_new(const fmu_logger *logger, const char *fn, const char *token_name,
                               const char *token)
{
    if (token == NULL || strcmp(token, fmu_token) != 0) {
        fmu_log(logger, FMU_ERROR, fn,
                "%s \"%.100s\" is not this FMU's \"%s\" (the modelDescription.xml and the "
                "binary do not belong together)",
                token_name, token ? token : "(null)", fmu_token);
        return NULL;
    }
    if (!table_ok(logger, fn))
        return NULL;
    fmu_instance *inst = calloc(1, sizeof *inst);
    if (inst == NULL) {
        fmu_log(logger, FMU_ERROR, fn, "out of memory (%zu bytes for the instance)", sizeof *inst);
        return NULL;
    }
    inst->logger = *logger;
    int st = core_init(&inst->core);
    if (st != DCT_OK) {
        fmu_log(logger, FMU_ERROR, fn,
                "the FMU's own parameter set fails the plant's check (dct_plant_init: %d)", st);
        free(inst);
        return NULL;
    }
    inst->magic = FMU_INSTANCE_MAGIC;
    fmu_log(&inst->logger, FMU_OK, fn, "instance \"%s\": %u variables, plant step %g s",
            inst->logger.name, fmu_n_vars, inst->core.plant.effective.solver.step_s);
    return inst;
}

void fmu_instance_free(fmu_instance *inst)
{
    if (!fmu_instance_ok(inst))
        return;
    inst->magic = 0;
    free(inst);
}

int fmu_instance_ok(const fmu_instance *inst)
{
    return inst != NULL && inst->magic == FMU_INSTANCE_MAGIC;
}

fmu_status fmu_set_debug_logging(fmu_instance *inst, const char *fn, int logging_on,
                                 size_t n_categories, const char *const categories[])
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    if (n_categories > 0 && categories == NULL)
        return fail(inst, fn, "categories is NULL with nCategories = %zu", n_categories);
    fmu_status st = FMU_OK;
    int events = n_categories == 0; /* none named: all of them */
    for (size_t i = 0; i < n_categories; i++) {
        const char *c = categories[i];
        if (c != NULL && strcmp(c, FMU_LOG_EVENTS) == 0) {
            events = 1;
        } else if (c == NULL || (strcmp(c, FMU_LOG_WARNING) != 0 && strcmp(c, FMU_LOG_ERROR) != 0)) {
            fmu_log(&inst->logger, FMU_WARNING, fn,
                    "unknown log category \"%.60s\" (this FMU's: " FMU_LOG_WARNING ", " FMU_LOG_ERROR
                    ", " FMU_LOG_EVENTS ")",
                    c ? c : "(null)");
            st = FMU_WARNING;
        }
    }
    inst->logger.logging_on = logging_on != 0;
    inst->logger.log_events = events;
    return st;
}

fmu_status fmu_not_in_mode(fmu_instance *inst, const char *fn)
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    switch (inst->core.mode) {
    case FMU_MODE_INSTANTIATED:
        return fail(inst, fn, "not allowed before initialization (the instance is only instantiated)");
    case FMU_MODE_INITIALIZATION:
        return fail(inst, fn, "not allowed in initialization mode (ExitInitializationMode first)");
    case FMU_MODE_STEP:
        return fail(inst, fn, "not allowed once initialized (the instance is in step mode)");
    case FMU_MODE_TERMINATED:
        return fail(inst, fn, "not allowed after Terminate (Reset or free the instance)");
    }
    return fail(inst, fn,
                "not allowed in the error state after a failed step or initialization (Reset or "
                "free the instance, or set a saved FMU state)");
}

fmu_status fmu_unsupported(fmu_instance *inst, const char *fn, const char *why)
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    return fail(inst, fn, "not supported: %s", why);
}

fmu_status fmu_error(fmu_instance *inst, const char *fn, const char *what)
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    return fail(inst, fn, "%s", what);
}

/* ------------------------------------------------------------------ */
/* Modes                                                               */
/* ------------------------------------------------------------------ */

double fmu_time(const fmu_instance *inst)
{
    const fmu_core *c = &inst->core;
    return c->base_time_s + (double)c->steps * c->plant.effective.solver.step_s;
}

fmu_status fmu_setup_experiment(fmu_instance *inst, const char *fn, double start_time,
                                int stop_time_defined, double stop_time)
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    fmu_core *c = &inst->core;
    if (c->mode != FMU_MODE_INSTANTIATED)
        return fmu_not_in_mode(inst, fn);
    if (!isfinite(start_time))
        return fail(inst, fn, "start time %g is not a finite number", start_time);
    if (stop_time_defined && !(isfinite(stop_time) && stop_time >= start_time))
        return fail(inst, fn, "stop time %g s is not a finite time after the start time %g s",
                    stop_time, start_time);
    c->base_time_s = start_time;
    c->steps = 0;
    c->stop_time_defined = stop_time_defined != 0;
    c->stop_time_s = stop_time_defined ? stop_time : 0.0;
    return FMU_OK;
}

/* from mode `from` to mode `to`; in any other mode an error */
static fmu_status change_mode(fmu_instance *inst, const char *fn, fmu_mode from, fmu_mode to)
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    if (inst->core.mode != (int)from)
        return fmu_not_in_mode(inst, fn);
    inst->core.mode = to;
    return FMU_OK;
}

fmu_status fmu_enter_initialization(fmu_instance *inst, const char *fn)
{
    return change_mode(inst, fn, FMU_MODE_INSTANTIATED, FMU_MODE_INITIALIZATION);
}

/* "changed: a = 1, b = 2" of the parameters that differ from fmu_params
 * (the faults: from 0): what the importer set that the plant's check may
 * have refused */
static void changed_params(const fmu_core *c, char *buf, size_t size)
{
    const size_t par0 = offsetof(dct_plant, params);
    size_t used = 0;
    int named = 0, more = 0;
    buf[0] = '\0';
    for (unsigned int i = 0; i < fmu_n_vars; i++) {
        const fmu_var *v = &fmu_vars[i];
        if (v->kind != FMU_VAR_PARAM_FIXED && v->kind != FMU_VAR_PARAM_TUNABLE)
            continue;
        double now, was = 0.0;
        memcpy(&now, (const char *)&c->plant + v->offset, sizeof now);
        if (v->offset >= par0 && v->offset < par0 + sizeof(dct_params))
            memcpy(&was, (const char *)&fmu_params + (v->offset - par0), sizeof was);
        if (memcmp(&now, &was, sizeof now) == 0)
            continue;
        if (named == FMU_CHANGED_NAMED) {
            more++;
            continue;
        }
        int k = snprintf(buf + used, size - used, "%s%s = %.17g", named ? ", " : "; changed: ",
                         v->name, now);
        if (k < 0 || (size_t)k >= size - used)
            break;
        used += (size_t)k;
        named++;
    }
    if (more > 0 && used < size)
        snprintf(buf + used, size - used, " and %d more", more);
}

fmu_status fmu_exit_initialization(fmu_instance *inst, const char *fn)
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    fmu_core *c = &inst->core;
    if (c->mode != FMU_MODE_INITIALIZATION)
        return fmu_not_in_mode(inst, fn);
    /* the inputs set so far: dct_plant_init puts the defaults back */
    dct_inputs given;
    memcpy(&given, &c->plant.inputs, sizeof given);
    int st = dct_plant_init(&c->plant);
    if (st == DCT_ERR_PARAM) {
        char changed[512];
        changed_params(c, changed, sizeof changed);
        c->mode = FMU_MODE_ERROR;
        return fail(inst, fn,
                    "parameter check failed: the plant core refused the parameter set (a value "
                    "outside its physical range, see check_params in plant/csrc/plant.c)%s",
                    changed);
    }
    if (st == DCT_OK)
        st = dct_plant_reset(&c->plant, &c->initial);
    if (st != DCT_OK) {
        c->mode = FMU_MODE_ERROR;
        return fail(inst, fn, "the plant's initialization failed (status %d)", st);
    }
    /* as plant/simulate.py: defaults, reset (which sets engine_on from the
     * initial conditions), then the first inputs written, not yet applied */
    double *in = (double *)&c->plant.inputs;
    const double *was = (const double *)&given;
    for (size_t i = 0; i < FMU_N_INPUTS; i++)
        if (c->input_set[i])
            in[i] = was[i];
    memset(c->input_set, 0, sizeof c->input_set);
    c->steps = 0;
    c->mode = FMU_MODE_STEP;
    fmu_log(&inst->logger, FMU_OK, fn, "initialized at t=%g s: %g km/h, plant step %g s",
            fmu_time(inst), c->initial.vehicle_speed_kmh, c->plant.effective.solver.step_s);
    return FMU_OK;
}

fmu_status fmu_terminate(fmu_instance *inst, const char *fn)
{
    fmu_status st = change_mode(inst, fn, FMU_MODE_STEP, FMU_MODE_TERMINATED);
    if (st == FMU_OK)
        fmu_log(&inst->logger, FMU_OK, fn, "terminated at t=%g s", fmu_time(inst));
    return st;
}

fmu_status fmu_reset(fmu_instance *inst, const char *fn)
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    int st = core_init(&inst->core);
    if (st != DCT_OK) {
        inst->core.mode = FMU_MODE_ERROR;
        return fail(inst, fn, "the FMU's own parameter set fails the plant's check (%d)", st);
    }
    fmu_log(&inst->logger, FMU_OK, fn, "reset to the instantiated state");
    return FMU_OK;
}

/* ------------------------------------------------------------------ */
/* Variables                                                           */
/* ------------------------------------------------------------------ */

static fmu_status no_such_vr(fmu_instance *inst, const char *fn, unsigned long vr)
{
    return fail(inst, fn, "value reference %lu does not exist (this FMU has 0..%u)", vr,
                fmu_n_vars - 1);
}

static fmu_status get_real(fmu_instance *inst, const char *fn, unsigned long vr, double *value)
{
    if (vr >= fmu_n_vars)
        return no_such_vr(inst, fn, vr);
    const fmu_var *v = &fmu_vars[vr];
    *value = v->kind == FMU_VAR_TIME ? fmu_time(inst) : *var_ptr(&inst->core, v);
    return FMU_OK;
}

static fmu_status check_real(fmu_instance *inst, const char *fn, unsigned long vr, double value)
{
    const fmu_core *c = &inst->core;
    if (vr >= fmu_n_vars)
        return no_such_vr(inst, fn, vr);
    const fmu_var *v = &fmu_vars[vr];
    if (c->mode == FMU_MODE_TERMINATED || c->mode == FMU_MODE_ERROR)
        return fmu_not_in_mode(inst, fn);
    int before_end = c->mode == FMU_MODE_INSTANTIATED || c->mode == FMU_MODE_INITIALIZATION;
    switch (v->kind) {
    case FMU_VAR_TIME:
        return fail(inst, fn, "%s cannot be set: it is the independent variable (the FMU's time)",
                    v->name);
    case FMU_VAR_OUTPUT:
        return fail(inst, fn, "%s cannot be set: it is an output", v->name);
    case FMU_VAR_PARAM_FIXED:
    case FMU_VAR_INITIAL:
        if (!before_end)
            return fail(inst, fn,
                        "%s %s cannot be set once initialized: only before "
                        "ExitInitializationMode",
                        kind_word(v->kind), v->name);
        break;
    }
    if (!isfinite(value))
        return fail(inst, fn, "%s %s = %g refused: not a finite number", kind_word(v->kind),
                    v->name, value);
    if (value < v->min || value > v->max)
        return fail(inst, fn, "%s %s = %.17g refused: outside its range [%g, %g]",
                    kind_word(v->kind), v->name, value, v->min, v->max);
    return FMU_OK;
}

/* writes a value check_real accepted; a tunable parameter while stepping goes
 * through dct_plant_prepare (refused: the old value back) */
static fmu_status put_real(fmu_instance *inst, const char *fn, unsigned long vr, double value)
{
    fmu_core *c = &inst->core;
    const fmu_var *v = &fmu_vars[vr];
    double *p = var_ptr(c, v);
    int before_end = c->mode == FMU_MODE_INSTANTIATED || c->mode == FMU_MODE_INITIALIZATION;
    if (v->kind == FMU_VAR_INPUT && before_end)
        c->input_set[input_index(v)] = 1; /* written again after the reset */
    if (v->kind != FMU_VAR_PARAM_TUNABLE || before_end) {
        /* parameters set before the end of initialization are checked there */
        *p = value;
        return FMU_OK;
    }
    /* a tunable parameter while stepping: in effect from the next step, if
     * the plant's check accepts it (refused: effective left as it was) */
    double old = *p;
    double step_was = c->plant.effective.solver.step_s;
    double time_was = fmu_time(inst);
    *p = value;
    if (dct_plant_prepare(&c->plant) != DCT_OK) {
        *p = old;
        return fail(inst, fn,
                    "tunable parameter %s = %.17g refused by the plant's parameter check "
                    "(dct_plant_prepare); it keeps %.17g",
                    v->name, value, old);
    }
    if (c->plant.effective.solver.step_s != step_was) {
        /* the time stays counted in steps of one length */
        c->base_time_s = time_was;
        c->steps = 0;
    }
    fmu_log(&inst->logger, FMU_OK, fn, "tunable parameter %s = %.17g in effect at t=%g s",
            v->name, value, time_was);
    return FMU_OK;
}

fmu_status fmu_get_reals(fmu_instance *inst, const char *fn, const uint32_t vrs[], size_t nvr,
                         double values[])
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    for (size_t i = 0; i < nvr; i++) {
        fmu_status st = get_real(inst, fn, vrs[i], &values[i]);
        if (st != FMU_OK)
            return st;
    }
    return FMU_OK;
}

fmu_status fmu_set_reals(fmu_instance *inst, const char *fn, const uint32_t vrs[], size_t nvr,
                         const double values[])
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    /* all checked before any is written: a refused call changes nothing
     * (but a tunable parameter the plant's check refuses, see put_real) */
    for (size_t i = 0; i < nvr; i++) {
        fmu_status st = check_real(inst, fn, vrs[i], values[i]);
        if (st != FMU_OK)
            return st;
    }
    for (size_t i = 0; i < nvr; i++) {
        fmu_status st = put_real(inst, fn, vrs[i], values[i]);
        if (st != FMU_OK)
            return st;
    }
    return FMU_OK;
}

fmu_status fmu_no_variables(fmu_instance *inst, const char *fn, const uint32_t vrs[], size_t nvr,
                            const char *vrs_name, const char *type, const char *real_type)
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    if (nvr == 0)
        return FMU_OK;
    if (vrs == NULL)
        return fail(inst, fn, "%s is NULL", vrs_name);
    unsigned long vr = vrs[0];
    if (vr >= fmu_n_vars)
        return no_such_vr(inst, fn, vr);
    return fail(inst, fn,
                "value reference %lu does not exist as a%s %s variable: it is the %s %s (this FMU "
                "has %s variables only)",
                vr, strchr("AEIOU", type[0]) ? "n" : "", type, real_type, fmu_vars[vr].name,
                real_type);
}

/* ------------------------------------------------------------------ */
/* Stepping                                                            */
/* ------------------------------------------------------------------ */

static void plant_error_message(fmu_instance *inst, const char *fn, int st, double t_fail)
{
    const dct_plant *pl = &inst->core.plant;
    int i = pl->error_index;
    if (st == DCT_ERR_STATE) {
        if (i >= 0 && (unsigned int)i < fmu_n_state_names) {
            const double *x = (const double *)&pl->state;
            fail(inst, fn, "state %s became %g at t=%.4f s", fmu_state_names[i], x[i], t_fail);
        } else {
            fail(inst, fn, "state #%d became non-finite at t=%.4f s", i, t_fail);
        }
    } else if (st == DCT_ERR_INPUT) {
        if (i >= 0 && (unsigned int)i < fmu_n_input_names && (size_t)i < FMU_N_INPUTS) {
            const double *u = (const double *)&pl->inputs;
            fail(inst, fn, "input %s is not finite: %g (at t=%.4f s)", fmu_input_names[i], u[i],
                 t_fail);
        } else {
            fail(inst, fn, "input #%d is not finite (at t=%.4f s)", i, t_fail);
        }
    } else {
        fail(inst, fn, "the plant's step failed with status %d at t=%.4f s", st, t_fail);
    }
}

fmu_status fmu_do_step(fmu_instance *inst, const char *fn, double t, double h, double *reached)
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    fmu_core *c = &inst->core;
    *reached = fmu_time(inst);
    if (c->mode != FMU_MODE_STEP)
        return fmu_not_in_mode(inst, fn);
    const double step = c->plant.effective.solver.step_s;
    if (!(isfinite(h) && h > 0.0))
        return fail(inst, fn, "communication step %g s is not a positive number of seconds", h);
    double n_real = nearbyint(h / step);
    if (!(n_real >= 1.0) || fabs(n_real * step - h) > FMU_STEP_RTOL * h)
        return fail(inst, fn, "communication step %.12g s is not a multiple of the plant's %.12g s step",
                    h, step);
    if (n_real > 9.0e15) /* past 2^53 the step count is no longer exact */
        return fail(inst, fn, "communication step %.12g s is too long", h);
    const double now = *reached;
    if (!(fabs(t - now) <= 0.5 * step))
        return fail(inst, fn,
                    "currentCommunicationPoint %.12g s is not the FMU's time %.12g s (more than "
                    "half a plant step apart)",
                    t, now);
    int64_t n = (int64_t)n_real;
    if (c->stop_time_defined) {
        double end = c->base_time_s + (double)(c->steps + n) * step;
        if (end > c->stop_time_s + 0.5 * step)
            return fail(inst, fn, "a step to t=%.12g s goes past the stop time %.12g s", end,
                        c->stop_time_s);
    }
    /* dct_plant_step takes an int: longer steps in parts (the outputs are
     * those of the last part, the state the same as in one call) */
    while (n > 0) {
        int part = n > INT_MAX ? INT_MAX : (int)n;
        double count_was = c->plant.step_count;
        int st = dct_plant_step(&c->plant, part);
        int64_t done = (int64_t)(c->plant.step_count - count_was);
        if (st != DCT_OK) {
            /* the step that ended non-finite is not counted: the time is the
             * last one with a finite state */
            double t_fail = c->base_time_s + (double)(c->steps + done) * step;
            c->steps += done > 0 ? done - 1 : 0;
            c->mode = FMU_MODE_ERROR;
            *reached = fmu_time(inst);
            plant_error_message(inst, fn, st, t_fail);
            return FMU_ERROR;
        }
        c->steps += done;
        n -= part;
    }
    *reached = fmu_time(inst);
    return FMU_OK;
}

/* ------------------------------------------------------------------ */
/* Saved FMU states                                                    */
/* ------------------------------------------------------------------ */

static int saved_ok(const void *state)
{
    return state != NULL && ((const fmu_saved *)state)->magic == FMU_SAVED_MAGIC;
}

fmu_status fmu_state_get(fmu_instance *inst, const char *fn, void **state)
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    if (state == NULL)
        return fail(inst, fn, "FMUstate is NULL");
    if (inst->core.mode == FMU_MODE_ERROR)
        return fmu_not_in_mode(inst, fn);
    fmu_saved *s = *state;
    if (s != NULL && !saved_ok(s))
        return fail(inst, fn, "*FMUstate is not a state of this FMU (pass NULL for a new one)");
    if (s == NULL) {
        s = calloc(1, sizeof *s);
        if (s == NULL)
            return fail(inst, fn, "out of memory (%zu bytes for an FMU state)", sizeof *s);
        s->magic = FMU_SAVED_MAGIC;
    }
    memcpy(&s->core, &inst->core, sizeof s->core);
    *state = s;
    return FMU_OK;
}

fmu_status fmu_state_set(fmu_instance *inst, const char *fn, const void *state)
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    if (!saved_ok(state))
        return fail(inst, fn, "FMUstate is not a state of this FMU (NULL, freed or foreign)");
    const fmu_saved *s = state;
    memcpy(&inst->core, &s->core, sizeof inst->core);
    return FMU_OK;
}

fmu_status fmu_state_free(fmu_instance *inst, const char *fn, void **state)
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    if (state == NULL || *state == NULL)
        return FMU_OK;
    if (!saved_ok(*state))
        return fail(inst, fn, "FMUstate is not a state of this FMU (freed twice or foreign)");
    fmu_saved *s = *state;
    s->magic = 0;
    free(s);
    *state = NULL;
    return FMU_OK;
}

/* The serialized form, all integers in this machine's byte order:
 *   8  magic "DCT-FMUS"
 *   4  format version
 *   4  byte order mark 0x01020304 (another machine's reads differently)
 *   8  sizeof(dct_plant), 8 sizeof(fmu_core): the same sources and platform
 *   4  token length, then the token (no NUL): the same variables and parameters
 *   sizeof(fmu_core) the copy
 *   8  FNV-1a 64 of all the bytes before it: the buffer undamaged */
#define SER_FORMAT 1u
#define SER_BOM 0x01020304u
#define SER_HEAD 36u
static const char ser_magic[8] = {'D', 'C', 'T', '-', 'F', 'M', 'U', 'S'};

static size_t ser_size(void)
{
    return SER_HEAD + strlen(fmu_token) + sizeof(fmu_core) + 8u;
}

static uint64_t fnv1a(const unsigned char *p, size_t n)
{
    uint64_t h = 14695981039346656037ull;
    for (size_t i = 0; i < n; i++) {
        h ^= p[i];
        h *= 1099511628211ull;
    }
    return h;
}

static void put_u32(unsigned char *p, uint32_t x) { memcpy(p, &x, sizeof x); }
static void put_u64(unsigned char *p, uint64_t x) { memcpy(p, &x, sizeof x); }
static uint32_t get_u32(const unsigned char *p)
{
    uint32_t x;
    memcpy(&x, p, sizeof x);
    return x;
}
static uint64_t get_u64(const unsigned char *p)
{
    uint64_t x;
    memcpy(&x, p, sizeof x);
    return x;
}

fmu_status fmu_state_size(fmu_instance *inst, const char *fn, const void *state, size_t *size)
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    if (!saved_ok(state))
        return fail(inst, fn, "FMUstate is not a state of this FMU (NULL, freed or foreign)");
    if (size == NULL)
        return fail(inst, fn, "size is NULL");
    *size = ser_size();
    return FMU_OK;
}

fmu_status fmu_state_serialize(fmu_instance *inst, const char *fn, const void *state,
                               unsigned char *buf, size_t size)
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    if (!saved_ok(state))
        return fail(inst, fn, "FMUstate is not a state of this FMU (NULL, freed or foreign)");
    const size_t need = ser_size();
    if (buf == NULL || size < need)
        return fail(inst, fn, "buffer of %zu bytes is too small: the state takes %zu", size, need);
    const fmu_saved *s = state;
    const size_t tlen = strlen(fmu_token);
    memcpy(buf, ser_magic, sizeof ser_magic);
    put_u32(buf + 8, SER_FORMAT);
    put_u32(buf + 12, SER_BOM);
    put_u64(buf + 16, sizeof(dct_plant));
    put_u64(buf + 24, sizeof(fmu_core));
    put_u32(buf + 32, (uint32_t)tlen);
    memcpy(buf + SER_HEAD, fmu_token, tlen);
    memcpy(buf + SER_HEAD + tlen, &s->core, sizeof s->core);
    put_u64(buf + need - 8, fnv1a(buf, need - 8));
    return FMU_OK;
}

fmu_status fmu_state_deserialize(fmu_instance *inst, const char *fn, const unsigned char *buf,
                                 size_t size, void **state)
{
    if (!fmu_instance_ok(inst))
        return FMU_ERROR;
    if (state == NULL)
        return fail(inst, fn, "FMUstate is NULL");
    if (*state != NULL && !saved_ok(*state))
        return fail(inst, fn, "*FMUstate is not a state of this FMU (pass NULL for a new one)");
    if (buf == NULL || size < SER_HEAD)
        return fail(inst, fn, "%zu bytes are too few for a serialized FMU state (header: %u)",
                    buf ? size : 0, SER_HEAD);
    if (memcmp(buf, ser_magic, sizeof ser_magic) != 0)
        return fail(inst, fn, "not a serialized state of this plant's FMU (wrong magic)");
    if (get_u32(buf + 12) != SER_BOM)
        return fail(inst, fn, "the state was serialized on a machine of another byte order");
    if (get_u32(buf + 8) != SER_FORMAT)
        return fail(inst, fn, "serialization format %u, this FMU reads %u", get_u32(buf + 8),
                    SER_FORMAT);
    if (get_u64(buf + 16) != sizeof(dct_plant))
        return fail(inst, fn,
                    "the state's dct_plant has %llu bytes, this FMU's %zu (another build of the "
                    "plant)",
                    (unsigned long long)get_u64(buf + 16), sizeof(dct_plant));
    if (get_u64(buf + 24) != sizeof(fmu_core))
        return fail(inst, fn, "the state's instance data has %llu bytes, this FMU's %zu",
                    (unsigned long long)get_u64(buf + 24), sizeof(fmu_core));
    const size_t tlen = strlen(fmu_token);
    const uint32_t their = get_u32(buf + 32);
    if (their != tlen || size < SER_HEAD + (size_t)their ||
        memcmp(buf + SER_HEAD, fmu_token, tlen) != 0) {
        size_t shown = size >= SER_HEAD + (size_t)their ? their : size - SER_HEAD;
        return fail(inst, fn, "the state's token \"%.*s\" is not this FMU's \"%s\"",
                    (int)(shown > 100 ? 100 : shown), (const char *)buf + SER_HEAD, fmu_token);
    }
    const size_t need = ser_size();
    if (size != need)
        return fail(inst, fn, "%zu bytes, a serialized state of this FMU has %zu", size, need);
    if (get_u64(buf + need - 8) != fnv1a(buf, need - 8))
        return fail(inst, fn, "checksum mismatch: the serialized state is damaged");
    fmu_core core;
    memcpy(&core, buf + SER_HEAD + tlen, sizeof core);
    if (core.mode < FMU_MODE_INSTANTIATED || core.mode > FMU_MODE_TERMINATED || core.steps < 0 ||
        !(core.plant.step_count >= 0.0 && core.plant.step_count <= 9.0e15))
        return fail(inst, fn, "the serialized state has an impossible mode %d or step count",
                    core.mode);
    /* the parameters and faults pass the plant's check, and what the step
     * uses (effective, derived) is what they give: a state written by this
     * FMU always is (the checksum only tells damage from a valid buffer) */
    dct_plant *check = malloc(sizeof *check);
    if (check == NULL)
        return fail(inst, fn, "out of memory (%zu bytes to check an FMU state)", sizeof *check);
    memcpy(check, &core.plant, sizeof *check);
    int prepared = dct_plant_prepare(check);
    int same = prepared == DCT_OK &&
               memcmp(&check->effective, &core.plant.effective, sizeof check->effective) == 0 &&
               memcmp(&check->derived, &core.plant.derived, sizeof check->derived) == 0;
    free(check);
    if (prepared != DCT_OK)
        return fail(inst, fn, "the serialized state's parameters or faults fail the plant's check");
    if (!same)
        return fail(inst, fn, "the serialized state's derived values do not follow from its "
                              "parameters");
    fmu_saved *s = *state;
    if (s == NULL) {
        s = calloc(1, sizeof *s);
        if (s == NULL)
            return fail(inst, fn, "out of memory (%zu bytes for an FMU state)", sizeof *s);
        s->magic = FMU_SAVED_MAGIC;
    }
    memcpy(&s->core, &core, sizeof core);
    *state = s;
    return FMU_OK;
}
