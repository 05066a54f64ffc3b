/*
 * rt_xcp_send.h - the XCP slave's sender in C: DTOs out of the DAQ ring,
 * packed, framed (XCP on Ethernet) and sent on the socket Python opened, by
 * an ordinary thread of its own (never the tick's), with no Python between
 * the tick and the socket.
 *
 * Python (rt_loop/measure/xcp/transport.py) keeps the command channel: it
 * receives the commands, runs the protocol (the Slave) and hands its
 * responses and events to rt_xcp_send_packets, which frames and sends them
 * through the same path as the DTOs. So the sender owns what both share:
 *   - the packet counter CTR of the XCP on Ethernet header: the slave counts
 *     every packet it sends (responses, errors, events, DTOs) in one
 *     sequence, 0 at each new master; a frame gets its CTR when it is put on
 *     the socket or into the TCP queue, under the sender's mutex, so the
 *     master sees the counter increase in the order the packets come;
 *   - the master: over UDP its address (the last CONNECT's, set by Python),
 *     over TCP the accepted connection's descriptor (Python closes it only
 *     after handing the sender -1);
 *   - the TCP queue (RT_XCP_TCP_QUEUE_BYTES: a master that reads slowly
 *     never blocks the sender; a frame that does not fit is dropped and
 *     counted, a frame is never cut).
 * The mutex is taken only inside these functions (Python calls them with
 * the GIL released) and by the sender thread; the tick never takes it.
 *
 * The DTO layout (which list runs, has a timestamp, its absolute number,
 * the identification field's first PID, each ODT's data bytes) is what the
 * Slave answered the master; Python hands it over whenever it changes
 * (rt_xcp_sender_set_layout). A DTO whose list is not running in it, or
 * whose ODT does not match it (a DTO of an older configuration), is dropped
 * and counted. A DTO packet: [PID = first_pid + odt, 0, daq lo, daq hi]
 * (relative ODT number, absolute DAQ list number, word aligned), in the
 * first ODT of a list with timestamps the low 32 bits of its tick's
 * deadline in us, then the ODT's bytes. Several frames go into one UDP
 * datagram, up to RT_XCP_UDP_PAYLOAD bytes.
 *
 * When the ring's dropped count grew since the sender last looked and a
 * list runs, the master gets the event EV_DAQ_OVERLOAD ([0xFD, 0x06]).
 *
 * The DTO delay, from the tick's deadline (the DTO's time_ns) to the clock
 * read just before the packet is handed to the socket (sendto; over TCP
 * the send that starts the batch), goes into a histogram of 1 us bins.
 *
 * Read by cffi: plain structs, integer #defines, prototypes.
 */
#ifndef RT_XCP_SEND_H
#define RT_XCP_SEND_H

#include <stdint.h>

#include "rt_loop.h"

#define RT_XCP_UDP 0
#define RT_XCP_TCP 1
#define RT_XCP_HEADER_BYTES 4         /* LEN u16, CTR u16, little endian */
#define RT_XCP_DTO_ID_BYTES 4         /* [PID, fill, daq lo, daq hi] */
#define RT_XCP_TIMESTAMP_BYTES 4
#define RT_XCP_MAX_PACKET 256         /* bytes of one packet at most (MAX_CTO, MAX_DTO) */
#define RT_XCP_UDP_PAYLOAD 1472       /* an Ethernet payload less IPv4 and UDP headers */
#define RT_XCP_TCP_QUEUE_BYTES 1048576
#define RT_XCP_BATCH 64               /* DTOs popped from the ring at once */
#define RT_XCP_DELAY_BINS 100000      /* 1 us bins, 0 .. 99.999 ms; the last holds all above */
#define RT_XCP_ERRNO_SLOTS 160        /* send errors by errno (0: any errno beyond) */
#define RT_XCP_POLL_US 200            /* the sender's pause when the ring ran dry, lists running */
#define RT_XCP_IDLE_US 5000           /* ... and when no list runs */

/* one DAQ list as the master configured it */
typedef struct {
    uint8_t running;                  /* 1: its DTOs are sent */
    uint8_t timestamp;                /* 1: its first ODT carries the timestamp */
    uint8_t first_pid;                /* PID of its ODT 0 (relative ODT numbers: 0) */
    uint8_t reserved;
    uint16_t daq;                     /* its absolute DAQ list number */
    uint16_t n_odts;
    uint32_t first_size;              /* its ODTs' data bytes: sizes[first_size ..] */
} rt_xcp_list;

typedef struct {
    uint32_t n_lists;                 /* lists of the loop's list numbers 0 .. n_lists - 1 */
    rt_xcp_list lists[RT_DAQ_MAX_LISTS];
    uint16_t sizes[RT_DAQ_MAX_ODTS];  /* data bytes of each ODT (the loop's copy: rt_dto.len) */
} rt_xcp_layout;

/* what the sender counted (rt_xcp_sender_read) */
typedef struct {
    uint64_t packets_out;             /* frames sent or queued (TCP), every kind */
    uint64_t dtos_out;                /* ... of them DTOs */
    uint64_t dtos_packed;             /* DTO packets made from the ring */
    uint64_t not_running;             /* DTOs of a list not running (any more) */
    uint64_t stale;                   /* DTOs not matching their list's ODTs */
    uint64_t overload_events;         /* EV_DAQ_OVERLOAD made */
    uint64_t no_master;               /* packets made while no master was there */
    uint64_t would_block;             /* UDP: packets the socket could not take now */
    uint64_t queue_full;              /* TCP: frames the queue could not take */
    uint64_t send_errors[RT_XCP_ERRNO_SLOTS];   /* by errno (UDP: packets, TCP: sends) */
    uint64_t datagrams;               /* UDP datagrams / TCP sends made */
    uint64_t wakeups;                 /* the sender thread's rounds */
    uint64_t delays;                  /* DTO delays measured */
    int64_t delay_max_ns;
    int64_t delay_sum_ns;
    uint64_t ring_dropped;            /* the ring's dropped count when last looked at */
    uint32_t layouts;                 /* layouts handed over */
    int32_t running;                  /* 1 while the thread runs */
    int32_t error;                    /* errno of a failed start (pthread_create) */
    uint16_t ctr;                     /* the next packet's CTR */
    uint16_t reserved;
} rt_xcp_send_stats;

typedef struct rt_xcp_sender rt_xcp_sender;

/* a sender reading `ring` (the loop's daq_ring), or, with ring NULL, a ring
 * of its own that rt_xcp_sender_feed fills (a DAQ producer in Python);
 * sending with `protocol` (RT_XCP_UDP: on the UDP socket `fd`; RT_XCP_TCP:
 * on the connection rt_xcp_sender_set_tcp gives). NULL when out of memory
 * or for a bad argument. */
rt_xcp_sender *rt_xcp_sender_new(rt_daq_ring *ring, int protocol, int fd);
/* stops the thread (if started) and frees the sender */
void rt_xcp_sender_free(rt_xcp_sender *s);
/* starts the thread; poll_us: its pause when the ring ran dry (0: RT_XCP_POLL_US);
 * 0, or -errno (also kept in stats.error) */
int rt_xcp_sender_start(rt_xcp_sender *s, int poll_us);
/* asks the thread to stop (ending its pause) and joins it */
void rt_xcp_sender_stop(rt_xcp_sender *s);

/* UDP: the master's address (family AF_INET or AF_INET6, the address as
 * text, port, IPv6 scope); the CTR starts again at 0. 0, or -1 for an
 * address that does not parse (the master is then none). */
int rt_xcp_sender_set_peer(rt_xcp_sender *s, int family, const char *host, int port,
                           uint32_t scope_id);
/* UDP: no master */
void rt_xcp_sender_clear_peer(rt_xcp_sender *s);
/* TCP: the accepted connection's descriptor (-1: none); the queue is
 * emptied and the CTR starts again at 0. Once this returns the sender no
 * longer uses the previous descriptor. */
void rt_xcp_sender_set_tcp(rt_xcp_sender *s, int fd);
/* the DTO layout from now on; 0, or -1 for a layout out of bounds (then
 * no list runs) */
int rt_xcp_sender_set_layout(rt_xcp_sender *s, const rt_xcp_layout *layout);

/* Python's packets (responses, errors, events): n packets, packet k of
 * lens[k] bytes (1 .. RT_XCP_MAX_PACKET) at data + the lengths before it;
 * framed with the CTR and sent like the DTOs. Returns the packets sent (or
 * queued); the others are counted (no master, would block, queue full,
 * errors). */
int rt_xcp_send_packets(rt_xcp_sender *s, const uint8_t *data, const uint16_t *lens, int n);
/* a DAQ producer in Python (a sender made with ring NULL): n DTOs into the
 * sender's own ring, `dropped` the producer's lost DTOs so far (the
 * overload indication); returns how many went in */
int rt_xcp_sender_feed(rt_xcp_sender *s, const rt_dto *dtos, int n, uint64_t dropped);

/* a consistent copy of the counts */
void rt_xcp_sender_read(rt_xcp_sender *s, rt_xcp_send_stats *out);
/* the DTO delay histogram (1 us bins): up to n bins copied; returns how many */
int rt_xcp_sender_delays(rt_xcp_sender *s, uint64_t *hist, int n);

/* the DTO packet of one ODT as the sender makes it: its length, -1 when
 * its list does not run in the layout, -2 when the ODT does not match it
 * (out: RT_XCP_MAX_PACKET bytes at least) */
int rt_xcp_pack_dto(const rt_xcp_layout *layout, const rt_dto *d, uint8_t *out);

#endif
