/*
 * tcu_link.c - the CAN contract between plant and TCU in one process
 * (offline.ContractLink), with the DBC's cycle times and quantisation.
 *
 * Each message due is packed into its frame and unpacked again by the table
 * codec (can_table.c, bit-exact with cantools' encode and decode), so every
 * value the TCU reads, and every command the plant gets, is the DBC signal's
 * value: limited to its range and rounded to its raw step. The plan (which
 * message is due in which period) and the signal routing come from
 * tcu_stub/fast.py, built from offline.py's own plan. CRC and AliveCounter
 * are not written: nothing on either side of the in-process link reads them.
 */
#include "tcu_fast.h"

static void transfer(const ct_table *table, const tcu_link_message *m, const double *from, double *to)
{
    double values[TCU_LINK_MAX_SIGNALS];
    uint8_t data[CT_MAX_LENGTH];
    for (int i = 0; i < m->n_signals; i++)
        values[i] = m->source[i] >= 0 ? from[m->source[i]] : 0.0;
    int len = ct_encode(table, m->msg, values, data);
    ct_decode(table, m->msg, data, len, values, NULL);
    for (int i = 0; i < m->n_signals; i++)
        if (m->target[i] >= 0)
            to[m->target[i]] = values[i];
}

void tcu_link_sensors(tcu_link *l, const double *outputs, int64_t k, double *sensors)
{
    int all = !l->received;
    for (int i = 0; i < l->n_plant; i++) {
        const tcu_link_message *m = &l->plant[i];
        if (all || k % m->divisor == m->offset)
            transfer(l->table, m, outputs, sensors);
    }
    l->received = 1;
}

void tcu_link_apply(const tcu_link *l, const double *commands, int64_t k, double *inputs)
{
    for (int i = 0; i < l->n_tcu; i++) {
        const tcu_link_message *m = &l->tcu[i];
        if (k % m->divisor == m->offset)
            transfer(l->table, m, commands, inputs);
    }
}
