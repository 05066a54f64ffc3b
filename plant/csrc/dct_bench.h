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

/* Step cost per component. The components, in the order of the assembly
 * (plant.c): 0 hydraulics (supply, both valves and chambers, the pistons; in
 * pressure_commanded mode the pistons alone), 1 clutches (K1 and K2 with
 * their friction elements), 2 engine, 3 driveline (differential and
 * half-shafts), 4 gearbox (shafts, meshes and the four synchronizers),
 * 5 tyres (three positions), 6 wheels (three, with brakes), 7 vehicle (body,
 * suspension, tyre loads), 8 thermal (the temperatures' effects and heat
 * balances). */
#define DCT_BENCH_N_COMPONENTS 9

/* Name of component i (0 .. DCT_BENCH_N_COMPONENTS - 1), NULL outside. */
const char *dct_bench_component_name(int i);

/* Times each component's output and advance functions, as one plant
 * sub-step calls them, on the plant's present state and applied inputs: the
 * couplings (torques, speeds, forces from the other components) are
 * evaluated once from that state and held; the component works on a copy of
 * its state, put back every few calls, so the plant is left unchanged.
 * About n calls per component in batches; ns_per_substep[i] (an array of
 * DCT_BENCH_N_COMPONENTS) receives the median over the batches of the
 * nanoseconds per call, i.e. per sub-step of params.solver.step_s /
 * params.solver.substeps. Returns DCT_OK, or DCT_ERR_INPUT when n < 1. */
int dct_bench_components(const dct_plant *plant, int n, double *ns_per_substep);

/* Compiler and flags this module was built with, for benchmark reports. */
const char *dct_bench_build_info(void);

#endif
