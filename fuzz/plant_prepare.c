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
 */
#include <stdlib.h>

#include "dct_plant.h"
#include "fmu_model.h"
#include "fuzz_input.h"

static dct_plant *plant;

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
    dct_plant_step(p, 1 + fz_u8(&in) % 4);
    dct_plant_update_outputs(p);
    patches(&in, p, fz_u8(&in) % 4);
    dct_plant_prepare(p);
    dct_plant_step(p, 2);
    return 0;
}
