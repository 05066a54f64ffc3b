/*
 * rt_ring.c - the loop's single-producer single-consumer rings (contract:
 * rt_loop.h): the push and pop functions Python and the bridge call; the
 * loop's own producers of the log and record rings are inlined into the
 * tick from rt_internal.h (those of the DAQ, fault event and scope rings:
 * rt_daq.c, rt_faults.c, rt_scope.c).
 *
 * Head is written by the producer (release) and read by the consumer
 * (acquire), tail the other way round; indices run freely over uint32_t,
 * masked by the power-of-two size. A full ring refuses the push and counts
 * it in dropped (written by the producer only). Rings: rx (producer: the
 * bridge thread, consumer: the loop), tx and log (producer: the loop,
 * consumer: a Python thread).
 */
#include "rt_internal.h"

_Static_assert((RT_RING_SIZE & (RT_RING_SIZE - 1)) == 0, "RT_RING_SIZE must be a power of two");
_Static_assert((RT_LOG_SIZE & (RT_LOG_SIZE - 1)) == 0, "RT_LOG_SIZE must be a power of two");
_Static_assert((RT_REC_SIZE & (RT_REC_SIZE - 1)) == 0, "RT_REC_SIZE must be a power of two");
_Static_assert((RT_DAQ_RING_SIZE & (RT_DAQ_RING_SIZE - 1)) == 0, "RT_DAQ_RING_SIZE: a power of two");
_Static_assert((RT_WRITE_RING_SIZE & (RT_WRITE_RING_SIZE - 1)) == 0,
               "RT_WRITE_RING_SIZE must be a power of two");
_Static_assert(sizeof(rt_loop) < 0xFFFFFFFFu, "offsets into rt_loop must fit 32 bits");

RT_DEFINE_PUSH_MANY(extern, rt_ring_push_many, rt_ring, rt_frame, frames, RT_RING_SIZE)
RT_DEFINE_PUSH_MANY(extern, rt_write_push_many, rt_write_ring, rt_write, writes, RT_WRITE_RING_SIZE)
RT_DEFINE_PUSH_MANY(extern, rt_fault_push_many, rt_fault_cmd_ring, rt_fault_cmd, cmds,
                    RT_FAULT_CMD_RING_SIZE)

RT_DEFINE_POP_MANY(extern, rt_ring_pop_many, rt_ring, rt_frame, frames, RT_RING_SIZE)
RT_DEFINE_POP_MANY(extern, rt_log_pop_many, rt_log_ring, rt_log_entry, entries, RT_LOG_SIZE)
RT_DEFINE_POP_MANY(extern, rt_rec_pop_many, rt_rec_ring, rt_sample, samples, RT_REC_SIZE)
RT_DEFINE_POP_MANY(extern, rt_daq_pop_many, rt_daq_ring, rt_dto, dtos, RT_DAQ_RING_SIZE)
RT_DEFINE_POP_MANY(extern, rt_fault_events_pop_many, rt_fault_event_ring, rt_fault_event, events,
                   RT_FAULT_EVENT_RING_SIZE)
RT_DEFINE_POP_MANY(extern, rt_scope_pop_many, rt_scope_ring, rt_scope_bucket, buckets,
                   RT_SCOPE_RING_SIZE)
RT_DEFINE_POP_MANY(extern, rt_capture_pop_many, rt_capture_ring, rt_capture_record, records,
                   RT_CAPTURE_RING_SIZE)

int rt_ring_push(rt_ring *r, const rt_frame *f)
{
    return rt_ring_push_many(r, f, 1) == 1 ? 0 : -1;
}

int rt_ring_pop(rt_ring *r, rt_frame *f)
{
    return rt_ring_pop_many(r, f, 1) == 1 ? 0 : -1;
}

int rt_log_pop(rt_log_ring *r, rt_log_entry *e)
{
    return rt_log_pop_many(r, e, 1) == 1 ? 0 : -1;
}
