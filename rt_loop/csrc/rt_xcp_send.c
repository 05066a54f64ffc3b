/*
 * rt_xcp_send.c - the XCP slave's sender thread (contract: rt_xcp_send.h):
 * the DAQ ring read, each DTO packed and framed with the slave's CTR, sent
 * on the UDP socket to the master's address or queued and sent on the TCP
 * connection; Python's responses and events through the same framing; the
 * overload event; the counts and the DTO delay histogram.
 *
 * An ordinary pthread (not SCHED_FIFO), signals blocked: it polls the ring
 * every poll_us while a list runs (RT_XCP_IDLE_US otherwise; a layout with
 * a running list or a stop ends the pause at once), so the tick makes no
 * system call for it. Everything but the ring (single consumer:
 * this thread) is under the sender's mutex, which only this file's
 * functions take, never across a return to Python.
 */
#include "rt_internal.h"
#include "rt_xcp_send.h"

#include <arpa/inet.h>
#include <errno.h>
#include <netinet/in.h>
#include <pthread.h>
#include <signal.h>
#include <stdlib.h>
#include <time.h>
#include <unistd.h>

#define PID_EV 0xFD
#define EV_DAQ_OVERLOAD 0x06
#define FIRST_CTO_PID 0xFC            /* DTO PIDs stay below the CTO packets' */
#define MAX_PENDING 512               /* DTO times waiting for their send */

struct rt_xcp_sender {
    rt_daq_ring *ring;                /* the loop's, or own_ring */
    rt_daq_ring *own_ring;            /* filled by rt_xcp_sender_feed */
    int protocol;                     /* RT_XCP_UDP, RT_XCP_TCP */
    int udp_fd;
    int poll_us;
    pthread_t thread;
    int started;
    _Atomic int stop;

    pthread_mutex_t mu;               /* all below */
    pthread_cond_t wake;              /* the thread's pause: ended early by a start or a stop */
    int tcp_fd;                       /* -1: no master (TCP) */
    int has_peer;                     /* UDP */
    struct sockaddr_storage peer;
    socklen_t peer_len;
    uint16_t ctr;
    rt_xcp_layout layout;
    int any_running;
    uint64_t seen_dropped;
    /* UDP: the datagram being filled */
    uint8_t dgram[RT_XCP_UDP_PAYLOAD];
    uint32_t dgram_len;
    uint32_t dgram_frames;
    uint32_t dgram_dtos;
    /* TCP: the queue, bytes q[q_start .. q_end - 1] */
    uint8_t *q;
    uint32_t q_start;
    uint32_t q_end;
    /* DTO times of the frames not sent yet (delay measured at their send) */
    int64_t pending[MAX_PENDING];
    uint32_t n_pending;
    rt_xcp_send_stats st;
    uint64_t hist[RT_XCP_DELAY_BINS];
};

RT_DEFINE_PUSH_MANY(static, dto_push_many, rt_daq_ring, rt_dto, dtos, RT_DAQ_RING_SIZE)

static int64_t now_ns(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (int64_t)t.tv_sec * 1000000000 + t.tv_nsec;
}

static void put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}

/* ---- packing ----------------------------------------------------------- */

int rt_xcp_pack_dto(const rt_xcp_layout *layout, const rt_dto *d, uint8_t *out)
{
    if (d->list >= layout->n_lists || !layout->lists[d->list].running)
        return -1;
    const rt_xcp_list *x = &layout->lists[d->list];
    if (d->odt >= x->n_odts || d->len != layout->sizes[x->first_size + d->odt])
        return -2;
    out[0] = (uint8_t)(x->first_pid + d->odt);
    out[1] = 0;
    put_u16(out + 2, x->daq);
    int n = RT_XCP_DTO_ID_BYTES;
    if (d->odt == 0 && x->timestamp) {
        /* the deadline in us, floor division (as for any int64), low 32 bits */
        int64_t us = d->time_ns / 1000;
        if (d->time_ns % 1000 < 0)
            us--;
        uint32_t ts = (uint32_t)(uint64_t)us;
        for (int k = 0; k < 4; k++)
            out[n + k] = (uint8_t)(ts >> (8 * k));
        n += RT_XCP_TIMESTAMP_BYTES;
    }
    memcpy(out + n, d->data, d->len);
    return n + d->len;
}

static uint32_t layout_size(const rt_xcp_layout *l, const rt_xcp_list *x, uint32_t odt)
{
    return l->sizes[x->first_size + odt];
}

static int layout_ok(const rt_xcp_layout *l)
{
    if (l->n_lists > RT_DAQ_MAX_LISTS)
        return 0;
    for (uint32_t i = 0; i < l->n_lists; i++) {
        const rt_xcp_list *x = &l->lists[i];
        if (x->first_size > RT_DAQ_MAX_ODTS || x->n_odts > RT_DAQ_MAX_ODTS - x->first_size ||
            (uint32_t)x->first_pid + x->n_odts > FIRST_CTO_PID)
            return 0;
        for (uint32_t o = 0; o < x->n_odts; o++) {
            uint32_t bytes = RT_XCP_DTO_ID_BYTES + layout_size(l, x, o);
            if (o == 0 && x->timestamp)
                bytes += RT_XCP_TIMESTAMP_BYTES;
            if (layout_size(l, x, o) > RT_DAQ_ODT_BYTES || bytes > RT_XCP_MAX_PACKET)
                return 0;
        }
    }
    return 1;
}

/* ---- sending (under mu) --------------------------------------------------- */

static int has_master(const rt_xcp_sender *s)
{
    return s->protocol == RT_XCP_UDP ? s->has_peer : s->tcp_fd >= 0;
}

static void count_errno(rt_xcp_sender *s, int err, uint64_t n)
{
    s->st.send_errors[err > 0 && err < RT_XCP_ERRNO_SLOTS ? err : 0] += n;
}

static void record_pending(rt_xcp_sender *s, int64_t at_ns)
{
    for (uint32_t k = 0; k < s->n_pending; k++) {
        int64_t d = at_ns - s->pending[k];
        if (d < 0)
            d = 0;
        int64_t bin = d / 1000;
        s->hist[bin < RT_XCP_DELAY_BINS ? bin : RT_XCP_DELAY_BINS - 1]++;
        if (d > s->st.delay_max_ns)
            s->st.delay_max_ns = d;
        s->st.delay_sum_ns += d;
        s->st.delays++;
    }
    s->n_pending = 0;
}

static void udp_flush(rt_xcp_sender *s)
{
    if (!s->dgram_frames)
        return;
    int64_t at = now_ns();
    ssize_t n = sendto(s->udp_fd, s->dgram, s->dgram_len, MSG_DONTWAIT,
                       (const struct sockaddr *)&s->peer, s->peer_len);
    if (n >= 0) {
        s->st.packets_out += s->dgram_frames;
        s->st.dtos_out += s->dgram_dtos;
        s->st.datagrams++;
        record_pending(s, at);
    } else {
        if (errno == EAGAIN || errno == EWOULDBLOCK)
            s->st.would_block += s->dgram_frames;
        else
            count_errno(s, errno, s->dgram_frames);
        s->n_pending = 0;
    }
    s->dgram_len = s->dgram_frames = s->dgram_dtos = 0;
}

static void tcp_flush(rt_xcp_sender *s)
{
    if (s->n_pending)
        record_pending(s, now_ns());
    while (s->tcp_fd >= 0 && s->q_start < s->q_end) {
        ssize_t n = send(s->tcp_fd, s->q + s->q_start, s->q_end - s->q_start,
                         MSG_DONTWAIT | MSG_NOSIGNAL);
        if (n > 0) {
            s->q_start += (uint32_t)n;
            s->st.datagrams++;
        } else if (n < 0 && errno == EINTR) {
            continue;
        } else if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
            break;
        } else {
            /* the master is gone: Python's receiver sees the end of its stream */
            count_errno(s, n < 0 ? errno : EPIPE, 1);
            s->q_start = s->q_end = 0;
            shutdown(s->tcp_fd, SHUT_RDWR);
            break;
        }
    }
    if (s->q_start == s->q_end)
        s->q_start = s->q_end = 0;
}

static void flush(rt_xcp_sender *s)
{
    if (s->protocol == RT_XCP_UDP)
        udp_flush(s);
    else
        tcp_flush(s);
}

/* one packet framed with the next CTR; time_ns >= 0: a DTO of that deadline */
static int emit(rt_xcp_sender *s, const uint8_t *packet, uint32_t len, int64_t time_ns, int dto)
{
    if (!has_master(s)) {
        s->st.no_master++;
        return 0;
    }
    uint32_t need = RT_XCP_HEADER_BYTES + len;
    uint8_t *at;
    if (s->protocol == RT_XCP_UDP) {
        if (s->dgram_len + need > RT_XCP_UDP_PAYLOAD)
            udp_flush(s);
        at = s->dgram + s->dgram_len;
        s->dgram_len += need;
        s->dgram_frames++;
        s->dgram_dtos += (uint32_t)dto;
    } else {
        if ((s->q_end - s->q_start) + need > RT_XCP_TCP_QUEUE_BYTES) {
            s->st.queue_full++;
            return 0;
        }
        if (s->q_end + need > RT_XCP_TCP_QUEUE_BYTES) {
            memmove(s->q, s->q + s->q_start, s->q_end - s->q_start);
            s->q_end -= s->q_start;
            s->q_start = 0;
        }
        at = s->q + s->q_end;
        s->q_end += need;
        s->st.packets_out++;
        s->st.dtos_out += (uint32_t)dto;
    }
    put_u16(at, (uint16_t)len);
    put_u16(at + 2, s->ctr++);
    memcpy(at + RT_XCP_HEADER_BYTES, packet, len);
    if (dto) {
        if (s->n_pending == MAX_PENDING)
            flush(s);
        s->pending[s->n_pending++] = time_ns;
    }
    return 1;
}

/* ---- the thread ------------------------------------------------------------ */

static void one_round(rt_xcp_sender *s, rt_dto *batch, int k, uint64_t dropped)
{
    uint8_t packet[RT_XCP_MAX_PACKET];
    s->st.wakeups++;
    for (int i = 0; i < k; i++) {
        int n = rt_xcp_pack_dto(&s->layout, &batch[i], packet);
        if (n == -1) {
            s->st.not_running++;
        } else if (n < 0) {
            s->st.stale++;
        } else {
            s->st.dtos_packed++;
            emit(s, packet, (uint32_t)n, batch[i].time_ns, 1);
        }
    }
    if (dropped != s->seen_dropped) {
        int grew = dropped > s->seen_dropped;
        s->seen_dropped = dropped;
        s->st.ring_dropped = dropped;
        if (grew && s->any_running) {
            static const uint8_t ev[2] = {PID_EV, EV_DAQ_OVERLOAD};
            s->st.overload_events++;
            emit(s, ev, sizeof ev, -1, 0);
        }
    }
    flush(s);
}

/* waits (mu held, released while waiting) for us, or until woken */
static void pause_locked(rt_xcp_sender *s, int us)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    t.tv_nsec += (long)(us % 1000000) * 1000;
    t.tv_sec += us / 1000000 + t.tv_nsec / 1000000000;
    t.tv_nsec %= 1000000000;
    pthread_cond_timedwait(&s->wake, &s->mu, &t);
}

static void *run(void *arg)
{
    rt_xcp_sender *s = arg;
    sigset_t all;
    sigfillset(&all);
    pthread_sigmask(SIG_BLOCK, &all, NULL);    /* Python's signals go to its own threads */
    rt_dto batch[RT_XCP_BATCH];
    while (!atomic_load_explicit(&s->stop, ACQUIRE)) {
        int k = rt_daq_pop_many(s->ring, batch, RT_XCP_BATCH);
        uint64_t dropped = atomic_load_explicit(A64(&s->ring->dropped), RELAXED);
        pthread_mutex_lock(&s->mu);
        one_round(s, batch, k, dropped);
        if (k < RT_XCP_BATCH && !atomic_load_explicit(&s->stop, ACQUIRE))
            pause_locked(s, s->any_running ? s->poll_us : RT_XCP_IDLE_US);
        pthread_mutex_unlock(&s->mu);
    }
    return NULL;
}

/* ---- the interface ----------------------------------------------------------- */

rt_xcp_sender *rt_xcp_sender_new(rt_daq_ring *ring, int protocol, int fd)
{
    if ((protocol != RT_XCP_UDP && protocol != RT_XCP_TCP) || (protocol == RT_XCP_UDP && fd < 0))
        return NULL;
    rt_xcp_sender *s = calloc(1, sizeof *s);
    if (!s)
        return NULL;
    if (!ring) {
        s->own_ring = calloc(1, sizeof *s->own_ring);
        if (!s->own_ring) {
            free(s);
            return NULL;
        }
        ring = s->own_ring;
    }
    if (protocol == RT_XCP_TCP && !(s->q = malloc(RT_XCP_TCP_QUEUE_BYTES))) {
        free(s->own_ring);
        free(s);
        return NULL;
    }
    s->ring = ring;
    s->protocol = protocol;
    s->udp_fd = protocol == RT_XCP_UDP ? fd : -1;
    s->tcp_fd = -1;
    s->poll_us = RT_XCP_POLL_US;
    /* DTOs already in the ring and losses before the sender are not its */
    s->seen_dropped = atomic_load_explicit(A64(&ring->dropped), RELAXED);
    s->st.ring_dropped = s->seen_dropped;
    pthread_condattr_t ca;
    pthread_condattr_init(&ca);
    pthread_condattr_setclock(&ca, CLOCK_MONOTONIC);
    pthread_mutex_init(&s->mu, NULL);
    pthread_cond_init(&s->wake, &ca);
    pthread_condattr_destroy(&ca);
    return s;
}

int rt_xcp_sender_start(rt_xcp_sender *s, int poll_us)
{
    if (!s || s->started)
        return -EINVAL;
    s->poll_us = poll_us > 0 ? poll_us : RT_XCP_POLL_US;
    atomic_store_explicit(&s->stop, 0, RELEASE);
    int rc = pthread_create(&s->thread, NULL, run, s);
    pthread_mutex_lock(&s->mu);
    s->st.error = rc;
    s->st.running = rc == 0;
    pthread_mutex_unlock(&s->mu);
    if (rc)
        return -rc;
    pthread_setname_np(s->thread, "xcp-tx");
    s->started = 1;
    return 0;
}

void rt_xcp_sender_stop(rt_xcp_sender *s)
{
    if (!s || !s->started)
        return;
    pthread_mutex_lock(&s->mu);
    atomic_store_explicit(&s->stop, 1, RELEASE);
    pthread_cond_signal(&s->wake);
    pthread_mutex_unlock(&s->mu);
    pthread_join(s->thread, NULL);
    s->started = 0;
    pthread_mutex_lock(&s->mu);
    s->st.running = 0;
    pthread_mutex_unlock(&s->mu);
}

void rt_xcp_sender_free(rt_xcp_sender *s)
{
    if (!s)
        return;
    rt_xcp_sender_stop(s);
    pthread_cond_destroy(&s->wake);
    pthread_mutex_destroy(&s->mu);
    free(s->q);
    free(s->own_ring);
    free(s);
}

int rt_xcp_sender_set_peer(rt_xcp_sender *s, int family, const char *host, int port,
                           uint32_t scope_id)
{
    if (!s)
        return -1;
    struct sockaddr_storage a;
    socklen_t len = 0;
    memset(&a, 0, sizeof a);
    int ok = port >= 0 && port <= 65535 && host != NULL;
    if (ok && family == AF_INET) {
        struct sockaddr_in *v4 = (struct sockaddr_in *)&a;
        v4->sin_family = AF_INET;
        v4->sin_port = htons((uint16_t)port);
        ok = inet_pton(AF_INET, host, &v4->sin_addr) == 1;
        len = sizeof *v4;
    } else if (ok && family == AF_INET6) {
        struct sockaddr_in6 *v6 = (struct sockaddr_in6 *)&a;
        v6->sin6_family = AF_INET6;
        v6->sin6_port = htons((uint16_t)port);
        v6->sin6_scope_id = scope_id;
        ok = inet_pton(AF_INET6, host, &v6->sin6_addr) == 1;
        len = sizeof *v6;
    } else {
        ok = 0;
    }
    pthread_mutex_lock(&s->mu);
    s->has_peer = ok;
    s->peer = a;
    s->peer_len = len;
    s->ctr = 0;
    s->dgram_len = s->dgram_frames = s->dgram_dtos = 0;
    s->n_pending = 0;
    pthread_mutex_unlock(&s->mu);
    return ok ? 0 : -1;
}

void rt_xcp_sender_clear_peer(rt_xcp_sender *s)
{
    if (!s)
        return;
    pthread_mutex_lock(&s->mu);
    s->has_peer = 0;
    pthread_mutex_unlock(&s->mu);
}

void rt_xcp_sender_set_tcp(rt_xcp_sender *s, int fd)
{
    if (!s)
        return;
    pthread_mutex_lock(&s->mu);
    s->tcp_fd = s->protocol == RT_XCP_TCP ? fd : -1;
    s->q_start = s->q_end = 0;
    s->n_pending = 0;
    s->ctr = 0;
    pthread_mutex_unlock(&s->mu);
}

int rt_xcp_sender_set_layout(rt_xcp_sender *s, const rt_xcp_layout *layout)
{
    if (!s || !layout)
        return -1;
    int ok = layout_ok(layout);
    pthread_mutex_lock(&s->mu);
    if (ok) {
        s->layout = *layout;
    } else {
        memset(&s->layout, 0, sizeof s->layout);
    }
    int was_running = s->any_running;
    s->any_running = 0;
    for (uint32_t i = 0; i < s->layout.n_lists; i++)
        s->any_running |= s->layout.lists[i].running;
    if (s->any_running && !was_running)
        pthread_cond_signal(&s->wake);    /* out of the idle pause: DTOs are coming */
    s->st.layouts++;
    pthread_mutex_unlock(&s->mu);
    return ok ? 0 : -1;
}

int rt_xcp_send_packets(rt_xcp_sender *s, const uint8_t *data, const uint16_t *lens, int n)
{
    int sent = 0;
    if (!s || (!data && n > 0) || (!lens && n > 0))
        return 0;
    pthread_mutex_lock(&s->mu);
    uint64_t before = s->st.packets_out;
    for (int k = 0; k < n; k++) {
        if (lens[k] >= 1 && lens[k] <= RT_XCP_MAX_PACKET)
            emit(s, data, lens[k], -1, 0);
        else
            count_errno(s, EMSGSIZE, 1);
        data += lens[k];
    }
    flush(s);
    sent = (int)(s->st.packets_out - before);
    pthread_mutex_unlock(&s->mu);
    return sent;
}

int rt_xcp_sender_feed(rt_xcp_sender *s, const rt_dto *dtos, int n, uint64_t dropped)
{
    if (!s || !s->own_ring || (!dtos && n > 0))
        return 0;
    int k = dto_push_many(s->own_ring, dtos, n);
    atomic_store_explicit(A64(&s->own_ring->dropped), dropped, RELAXED);
    return k;
}

void rt_xcp_sender_read(rt_xcp_sender *s, rt_xcp_send_stats *out)
{
    if (!s || !out)
        return;
    pthread_mutex_lock(&s->mu);
    *out = s->st;
    out->ctr = s->ctr;
    pthread_mutex_unlock(&s->mu);
}

int rt_xcp_sender_delays(rt_xcp_sender *s, uint64_t *hist, int n)
{
    if (n > RT_XCP_DELAY_BINS)
        n = RT_XCP_DELAY_BINS;
    if (n < 0 || !s || !hist)
        return 0;
    pthread_mutex_lock(&s->mu);
    memcpy(hist, s->hist, (size_t)n * sizeof *hist);
    pthread_mutex_unlock(&s->mu);
    return n;
}
