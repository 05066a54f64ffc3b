/*
 * dct_bench.h - step-cost measurement for the plant (dct-hil bench).
 *
 * Kept apart from the model: dct_bench.c is the only C file that reads a
 * clock, and it is not part of libdctplant.a (plant/csrc/Makefile).
 */
#ifndef DCT_BENCH_H
#define DCT_BENCH_H

#include "dct_plant.h"

/* Runs n single steps, dct_plant_step(plant, 1) each, and stores the cost of
 * each in step_ns[i] (CLOCK_MONOTONIC, nanoseconds). Stops after the first
 * step that returns a non-zero status and returns that status (the entries
 * after it are left as they were); returns 0 (DCT_OK) when all n succeed. */
int dct_bench_steps(dct_plant *plant, int n, double *step_ns);

/* Compiler and flags this module was built with, for benchmark reports. */
const char *dct_bench_build_info(void);

#endif
