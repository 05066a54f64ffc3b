/*
 * fmu_state.c - libFuzzer target: the FMU's serialized state read back
 * (plant/fmu/csrc/fmu_instance.c fmu_state_deserialize, behind
 * fmi2DeSerializeFMUstate and fmi3DeserializeFMUState).
 *
 * Two kinds of input, by the first byte:
 *   even  the bytes as they are: a damaged or foreign buffer, which must be
 *         refused with one logged line;
 *   odd   patches (offset, bytes) over a real serialized state of an
 *         instance in step mode, then the header's token and checksum made
 *         right again: the state a buggy or hostile writer could produce,
 *         which gets past the checksum. A state read back is set into the
 *         instance, which then steps and reads every variable: nothing it
 *         contains may make the plant read or write outside (a refused
 *         step is fine).
 */
#include <stdlib.h>

#include "fmu_instance.h"
#include "fuzz_input.h"

static fmu_instance *inst;
static void *pristine;           /* the instance's state before each input */
static unsigned char *tmpl;      /* its serialized form */
static size_t tmpl_size;

static void quiet(const fmu_logger *logger, fmu_status status, const char *category,
                  const char *message)
{
    (void)logger, (void)status, (void)category, (void)message;
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

static void setup(void)
{
    fmu_logger log = {quiet, (void (*)(void))quiet, NULL, 0, 0, "fuzz"};
    inst = fmu_instance_new(&log, "fuzz", "token", fmu_token);
    if (!inst || fmu_enter_initialization(inst, "fuzz") != FMU_OK ||
        fmu_exit_initialization(inst, "fuzz") != FMU_OK ||
        fmu_state_get(inst, "fuzz", &pristine) != FMU_OK ||
        fmu_state_size(inst, "fuzz", pristine, &tmpl_size) != FMU_OK)
        abort();
    tmpl = malloc(tmpl_size);
    if (!tmpl || fmu_state_serialize(inst, "fuzz", pristine, tmpl, tmpl_size) != FMU_OK)
        abort();
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    if (!inst)
        setup();
    fz_in in = {data, size};
    unsigned char *buf;
    size_t n;
    if (!(fz_u8(&in) & 1)) {
        n = fz_left(&in);
        buf = malloc(n ? n : 1);
        fz_bytes(&in, buf, n);
    } else {
        n = tmpl_size;
        buf = malloc(n);
        memcpy(buf, tmpl, n);
        while (fz_left(&in) > 0) {
            size_t off = fz_u32(&in) % n, len = 1 + fz_u8(&in) % 16;
            if (len > n - off)
                len = n - off;
            fz_bytes(&in, buf + off, len);
        }
        size_t tlen = strlen(fmu_token); /* the header and checksum right again */
        memcpy(buf, tmpl, 36 + tlen);
        uint64_t h = fnv1a(buf, n - 8);
        memcpy(buf + n - 8, &h, sizeof h);
    }
    void *state = NULL;
    if (fmu_state_deserialize(inst, "fuzz", buf, n, &state) == FMU_OK) {
        if (fmu_state_set(inst, "fuzz", state) != FMU_OK)
            abort();
        double reached = 0.0;
        double t = fmu_time(inst);
        double step = inst->core.plant.effective.solver.step_s;
        fmu_do_step(inst, "fuzz", t, 4 * step, &reached);
        static double values[4096];
        uint32_t vrs[64];
        for (uint32_t i = 0; i < 64; i++)
            vrs[i] = i;
        fmu_get_reals(inst, "fuzz", vrs, 64, values);
        fmu_state_free(inst, "fuzz", &state);
        if (fmu_state_set(inst, "fuzz", pristine) != FMU_OK)
            abort();
    }
    free(buf);
    return 0;
}
