/*
 * fmu_model.h - what the FMU's C code knows of the plant's variables.
 *
 * The FMU (plant/fmu/) wraps the plant's C core (plant/csrc/) for FMI 2.0
 * and FMI 3.0 co-simulation. Which of the plant's doubles are FMU variables
 * is decided in Python (plant/fmu/variables.py) from the C structs and the
 * parameter files, and written as C (fmu_variables.c, generated into the
 * FMU's sources/): this header is that file's contract. Offsets are
 * offsetof() expressions, so the sources compile for any platform.
 *
 * Value references: vr == index into fmu_vars; vr 0 is time.
 */
#ifndef FMU_MODEL_H
#define FMU_MODEL_H

#include <stddef.h>

#include "dct_plant.h"

#define FMU_VAR_TIME 0            /* independent: the plant's time_s */
#define FMU_VAR_INPUT 1           /* double in dct_plant (inputs.*) */
#define FMU_VAR_OUTPUT 2          /* double in dct_plant (outputs.*), read only */
#define FMU_VAR_PARAM_FIXED 3     /* double in dct_plant (params.*): set before initialization ends */
#define FMU_VAR_PARAM_TUNABLE 4   /* double in dct_plant (params.* or faults.*): also between
                                     steps (dct_plant_prepare checks it; refused: the old
                                     value back) */
#define FMU_VAR_INITIAL 5         /* double in dct_initial: the state the run starts from,
                                     set before initialization ends */

typedef struct {
    int kind;                     /* FMU_VAR_* */
    size_t offset;                /* bytes into dct_plant, or into dct_initial (FMU_VAR_INITIAL) */
    double start;                 /* the default car's value (inputs: dct_plant_init's) */
    double min;                   /* -INFINITY / INFINITY when unbounded */
    double max;
    const char *name;             /* as in modelDescription.xml */
} fmu_var;

extern const fmu_var fmu_vars[];
extern const unsigned int fmu_n_vars;

/* The parameters the FMU was built with (the default car, or --params):
 * every field of dct_params, point counts included. */
extern const dct_params fmu_params;

/* The initial conditions' defaults (start values of the FMU_VAR_INITIAL). */
extern const dct_initial fmu_initial;

/* Names for messages: dct_state's doubles in order (error_index of
 * DCT_ERR_STATE), dct_inputs' doubles in order (DCT_ERR_INPUT). */
extern const char *const fmu_state_names[];
extern const unsigned int fmu_n_state_names;
extern const char *const fmu_input_names[];
extern const unsigned int fmu_n_input_names;

/* modelDescription's guid (FMI 2) and instantiationToken (FMI 3): a digest
 * of the variables and the parameters; instantiating with another is refused. */
extern const char fmu_token[];

#endif
