/*
 * plant_prepare.c - libFuzzer target: the plant's parameter and fault
 * checks (dct_plant_init, dct_plant_prepare in plant/csrc) with arbitrary
 * parameter blobs.
 *
 * The default car's parameters (the FMU's generated table, fmu_params)
 * are patched by the input: (where, offset, length, bytes) over the
 * parameters, the physical faults or the inputs. dct_plant_init must
 * accept or refuse them (DCT_ERR_*); accepted, the plant steps; then a
 * second round of patches goes in while "running" through
 * dct_plant_prepare (refused: nothing changes) and the plant steps again.
 * A refused step is fine; reading or writing outside, or undefined
 * arithmetic (UBSan: float-to-int overflow, shifts), is a finding.
 *
 * The checks accept up to 1000 solver sub-steps times 1000 hydraulic
 * sub-steps: a million valve evaluations per step, the same code at a finer
 * step. The target steps only parameters within STEP_BUDGET hydraulic
 * sub-steps per step (the data's ranges allow 64 x 64, the car runs 1 x 2);
 * beyond it the checks still run. Without the budget the campaign spent
 * most of its time in the valve's loop (4,300 inputs/s against 61,600 with it, one worker).
 */
#include <stdlib.h>

#include "dct_plant.h"
#include "fmu_model.h"
#include "fuzz_input.h"

static dct_plant *plant;

#define STEP_BUDGET 64.0

static int affordable(const dct_plant *p)
{
    return p->effective.solver.substeps * p->effective.hydraulics.substeps <= STEP_BUDGET;
}

static void patches(fz_in *in, dct_plant *p, int n)
{
    for (int i = 0; i < n && fz_left(in) > 0; i++) {
        uint8_t where = fz_u8(in) % 3;
        uint8_t *base = where == 0 ? (uint8_t *)&p->params
                        : where == 1 ? (uint8_t *)&p->faults
                                     : (uint8_t *)&p->inputs;
        size_t span = where == 0 ? sizeof p->params
                      : where == 1 ? sizeof p->faults
                                   : sizeof p->inputs;
        size_t off = (fz_u16(in) % (span / 8)) * 8; /* whole doubles: every field is one */
        size_t len = 8 * (1 + fz_u8(in) % 2);
        if (len > span - off)
            len = span - off;
        fz_bytes(in, base + off, len);
    }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    if (!plant && !(plant = calloc(1, sizeof *plant)))
        abort();
    fz_in in = {data, size};
    dct_plant *p = plant;
    memset(p, 0, sizeof *p);
    memcpy(&p->params, &fmu_params, sizeof fmu_params);
    patches(&in, p, 1 + fz_u8(&in) % 8);
    int st = dct_plant_init(p);
    if (st != DCT_OK)
        return 0;
    int n = 1 + fz_u8(&in) % 4;
    if (affordable(p))
        dct_plant_step(p, n);
    dct_plant_update_outputs(p);
    patches(&in, p, fz_u8(&in) % 4);
    dct_plant_prepare(p);
    if (affordable(p))
        dct_plant_step(p, 2);
    return 0;
}
