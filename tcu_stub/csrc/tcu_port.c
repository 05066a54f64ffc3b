/*
 * tcu_port.c - where the C TCU node's frames come from and go to: a bound
 * CAN_RAW socket (SocketCAN, read and written without waiting), or a pair of
 * functions with a context each (frame rings), and the node's own
 * single-producer single-consumer rings that a Python bridge serves for the
 * other python-can interfaces.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <stddef.h>
#include <string.h>
#include <sys/socket.h>
#include <linux/can.h>

#include "tcu_node.h"

int tcu_port_recv(tcu_port *p, tcu_frame *f, int n)
{
    if (p->fd < 0)
        return p->recv != NULL ? p->recv(p->recv_ctx, f, n) : 0;
    int got = 0;
    while (got < n) {
        struct canfd_frame cf;
        ssize_t r = recv(p->fd, &cf, sizeof cf, MSG_DONTWAIT);
        if (r < 0) {
            if (errno == EINTR)
                continue;
            break;                    /* EAGAIN: nothing more waiting (errors too: next period) */
        }
        tcu_frame *o = &f[got];
        memset(o, 0, offsetof(tcu_frame, data));
        o->id = cf.can_id;
        if (r == CANFD_MTU) {
            o->len = cf.len > CT_MAX_LENGTH ? CT_MAX_LENGTH : cf.len;
            o->flags = TCU_FRAME_FD | ((cf.flags & CANFD_BRS) ? TCU_FRAME_BRS : 0);
        } else if (r == CAN_MTU) {
            o->len = cf.len > 8 ? 8 : cf.len;
        } else {
            continue;                 /* not a frame */
        }
        memcpy(o->data, cf.data, o->len);
        got++;
    }
    return got;
}

int tcu_port_send(tcu_port *p, const tcu_frame *f)
{
    if (p->fd < 0) {
        if (p->send == NULL)
            return -1;
        if (p->send(p->send_ctx, (tcu_frame *)f, 1) == 1)
            return 0;
        p->last_errno = ENOBUFS;
        return -1;
    }
    struct canfd_frame cf;
    memset(&cf, 0, sizeof cf);
    cf.can_id = f->id;
    cf.len = f->len;
    memcpy(cf.data, f->data, f->len);
    size_t size = CAN_MTU;
    if (f->flags & TCU_FRAME_FD) {
        if (!p->fd_frames) {
            p->last_errno = EINVAL;
            return -1;
        }
        size = CANFD_MTU;
        if (f->flags & TCU_FRAME_BRS)
            cf.flags |= CANFD_BRS;
    }
    for (;;) {
        ssize_t r = send(p->fd, &cf, size, MSG_DONTWAIT);
        if (r == (ssize_t)size)
            return 0;
        if (r < 0 && errno == EINTR)
            continue;
        p->last_errno = r < 0 ? errno : EIO;
        return -1;
    }
}

int tcu_ring_push_many(tcu_ring *r, const tcu_frame *f, int n)
{
    uint32_t head = r->head;
    uint32_t tail = __atomic_load_n(&r->tail, __ATOMIC_ACQUIRE);
    int room = (int)(TCU_RING_SIZE - (head - tail));
    int k = n < room ? n : room;
    for (int i = 0; i < k; i++)
        r->frames[(head + (uint32_t)i) & (TCU_RING_SIZE - 1)] = f[i];
    __atomic_store_n(&r->head, head + (uint32_t)k, __ATOMIC_RELEASE);
    if (k < n)
        r->dropped += (uint64_t)(n - k);
    return k;
}

int tcu_ring_pop_many(tcu_ring *r, tcu_frame *f, int n)
{
    uint32_t tail = r->tail;
    uint32_t head = __atomic_load_n(&r->head, __ATOMIC_ACQUIRE);
    int have = (int)(head - tail);
    int k = n < have ? n : have;
    for (int i = 0; i < k; i++)
        f[i] = r->frames[(tail + (uint32_t)i) & (TCU_RING_SIZE - 1)];
    __atomic_store_n(&r->tail, tail + (uint32_t)k, __ATOMIC_RELEASE);
    return k;
}

static int ring_pop(void *ctx, tcu_frame *f, int n) { return tcu_ring_pop_many(ctx, f, n); }
static int ring_push(void *ctx, tcu_frame *f, int n) { return tcu_ring_push_many(ctx, f, n); }

tcu_frame_fn tcu_ring_pop_fn(void) { return ring_pop; }
tcu_frame_fn tcu_ring_push_fn(void) { return ring_push; }

void tcu_frame_layout(int64_t *out)
{
    out[0] = sizeof(tcu_frame);
    out[1] = offsetof(tcu_frame, id);
    out[2] = offsetof(tcu_frame, len);
    out[3] = offsetof(tcu_frame, flags);
    out[4] = offsetof(tcu_frame, channel);
    out[5] = offsetof(tcu_frame, data);
}
