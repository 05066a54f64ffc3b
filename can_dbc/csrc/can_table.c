/*
 * can_table.c - the table-driven CAN codec of can_table.h.
 *
 * Bit layout as cantools reads a DBC. Byte B bit b is bit 8 B + b of the
 * frame (the DBC's numbering). A little-endian signal takes the bits start,
 * start + 1, ... upwards through the bytes, its LSB at start. A big-endian
 * signal has its MSB at start and runs down to bit 0 of that byte, then on
 * from bit 7 of the next byte.
 *
 * Checksums (AUTOSAR E2E Protocol Specification for P1 and P2):
 *   dct  CRC-8/SAE-J1850 (0x1D, init 0xFF, xorout 0xFF) over the identifier
 *        as two bytes (low, high), then every byte but the checksum's;
 *   P1   CRC-8/SAE-J1850's polynomial with start value and final XOR 0x00
 *        (the library's CRC chained from 0xFF and un-XORed, as Profile 1
 *        computes it) over the Data ID (by mode: both bytes low first; for
 *        ALT the low byte with an even counter, the high byte with an odd
 *        one; LOW the low byte; NIBBLE the low byte then 0x00) and every
 *        byte but the checksum's; the counter runs 0..14;
 *   P2   CRC-8H2F (0x2F, init 0xFF, xorout 0xFF) over every byte but the
 *        checksum's, then the Data ID data_id_list[counter]; counter 0..15;
 *   xor  the XOR of every byte but the checksum's;
 *   P5   a 3-byte header at byte h (crc_byte): CRC-16/CCITT-FALSE (0x1021,
 *        init 0xFFFF, no final XOR) over bytes 0 .. h-1, then h+2 .. len-1
 *        (the counter first), then the Data ID low and high byte, written
 *        low byte first into bytes h, h+1; the counter (0..255) in byte h+2;
 *   P4   a 12-byte header at byte h, each field big endian: the length
 *        (bytes, 16 bit), the counter (0..65535), the Data ID (32 bit, in
 *        data_id_list[0..3] low byte first), the CRC-32P4 (0xF4ACFB13,
 *        reflected, init and final XOR 0xFFFFFFFF) over bytes 0 .. h+7 and
 *        h+12 .. len-1;
 *   P7   a 20-byte header at byte h, each field big endian: the CRC-64
 *        (ECMA-182 0x42F0E1EBA9EA3693, reflected, init and final XOR all
 *        ones) over bytes 0 .. h-1 and h+8 .. len-1, the length (32 bit),
 *        the counter (32 bit), the Data ID (32 bit, as P4's).
 *
 * Floating point: every double converted to an integer has been limited to
 * the integer's range first; rint() rounds half to even in the default
 * rounding mode; expressions are written as cantools evaluates them (no
 * contraction into fused multiply-adds in ISO C mode, -std=c11).
 */
#define _POSIX_C_SOURCE 199309L   /* clock_gettime, for ct_bench_tick only */

#include <math.h>
#include <string.h>
#include <time.h>

#include "can_table.h"

#if defined(__GNUC__)
#define CT_INLINE static inline __attribute__((always_inline))
#else
#define CT_INLINE static inline
#endif

/* the next CRC register after one byte, register ^ byte -> value, for the
 * polynomials 0x1D (SAE-J1850) and 0x2F (8H2F); the tests check every CRC
 * against a bitwise computation */
static const uint8_t crc_1d[256] = {
    0x00, 0x1D, 0x3A, 0x27, 0x74, 0x69, 0x4E, 0x53, 0xE8, 0xF5, 0xD2, 0xCF,
    0x9C, 0x81, 0xA6, 0xBB, 0xCD, 0xD0, 0xF7, 0xEA, 0xB9, 0xA4, 0x83, 0x9E,
    0x25, 0x38, 0x1F, 0x02, 0x51, 0x4C, 0x6B, 0x76, 0x87, 0x9A, 0xBD, 0xA0,
    0xF3, 0xEE, 0xC9, 0xD4, 0x6F, 0x72, 0x55, 0x48, 0x1B, 0x06, 0x21, 0x3C,
    0x4A, 0x57, 0x70, 0x6D, 0x3E, 0x23, 0x04, 0x19, 0xA2, 0xBF, 0x98, 0x85,
    0xD6, 0xCB, 0xEC, 0xF1, 0x13, 0x0E, 0x29, 0x34, 0x67, 0x7A, 0x5D, 0x40,
    0xFB, 0xE6, 0xC1, 0xDC, 0x8F, 0x92, 0xB5, 0xA8, 0xDE, 0xC3, 0xE4, 0xF9,
    0xAA, 0xB7, 0x90, 0x8D, 0x36, 0x2B, 0x0C, 0x11, 0x42, 0x5F, 0x78, 0x65,
    0x94, 0x89, 0xAE, 0xB3, 0xE0, 0xFD, 0xDA, 0xC7, 0x7C, 0x61, 0x46, 0x5B,
    0x08, 0x15, 0x32, 0x2F, 0x59, 0x44, 0x63, 0x7E, 0x2D, 0x30, 0x17, 0x0A,
    0xB1, 0xAC, 0x8B, 0x96, 0xC5, 0xD8, 0xFF, 0xE2, 0x26, 0x3B, 0x1C, 0x01,
    0x52, 0x4F, 0x68, 0x75, 0xCE, 0xD3, 0xF4, 0xE9, 0xBA, 0xA7, 0x80, 0x9D,
    0xEB, 0xF6, 0xD1, 0xCC, 0x9F, 0x82, 0xA5, 0xB8, 0x03, 0x1E, 0x39, 0x24,
    0x77, 0x6A, 0x4D, 0x50, 0xA1, 0xBC, 0x9B, 0x86, 0xD5, 0xC8, 0xEF, 0xF2,
    0x49, 0x54, 0x73, 0x6E, 0x3D, 0x20, 0x07, 0x1A, 0x6C, 0x71, 0x56, 0x4B,
    0x18, 0x05, 0x22, 0x3F, 0x84, 0x99, 0xBE, 0xA3, 0xF0, 0xED, 0xCA, 0xD7,
    0x35, 0x28, 0x0F, 0x12, 0x41, 0x5C, 0x7B, 0x66, 0xDD, 0xC0, 0xE7, 0xFA,
    0xA9, 0xB4, 0x93, 0x8E, 0xF8, 0xE5, 0xC2, 0xDF, 0x8C, 0x91, 0xB6, 0xAB,
    0x10, 0x0D, 0x2A, 0x37, 0x64, 0x79, 0x5E, 0x43, 0xB2, 0xAF, 0x88, 0x95,
    0xC6, 0xDB, 0xFC, 0xE1, 0x5A, 0x47, 0x60, 0x7D, 0x2E, 0x33, 0x14, 0x09,
    0x7F, 0x62, 0x45, 0x58, 0x0B, 0x16, 0x31, 0x2C, 0x97, 0x8A, 0xAD, 0xB0,
    0xE3, 0xFE, 0xD9, 0xC4
};

static const uint8_t crc_2f[256] = {
    0x00, 0x2F, 0x5E, 0x71, 0xBC, 0x93, 0xE2, 0xCD, 0x57, 0x78, 0x09, 0x26,
    0xEB, 0xC4, 0xB5, 0x9A, 0xAE, 0x81, 0xF0, 0xDF, 0x12, 0x3D, 0x4C, 0x63,
    0xF9, 0xD6, 0xA7, 0x88, 0x45, 0x6A, 0x1B, 0x34, 0x73, 0x5C, 0x2D, 0x02,
    0xCF, 0xE0, 0x91, 0xBE, 0x24, 0x0B, 0x7A, 0x55, 0x98, 0xB7, 0xC6, 0xE9,
    0xDD, 0xF2, 0x83, 0xAC, 0x61, 0x4E, 0x3F, 0x10, 0x8A, 0xA5, 0xD4, 0xFB,
    0x36, 0x19, 0x68, 0x47, 0xE6, 0xC9, 0xB8, 0x97, 0x5A, 0x75, 0x04, 0x2B,
    0xB1, 0x9E, 0xEF, 0xC0, 0x0D, 0x22, 0x53, 0x7C, 0x48, 0x67, 0x16, 0x39,
    0xF4, 0xDB, 0xAA, 0x85, 0x1F, 0x30, 0x41, 0x6E, 0xA3, 0x8C, 0xFD, 0xD2,
    0x95, 0xBA, 0xCB, 0xE4, 0x29, 0x06, 0x77, 0x58, 0xC2, 0xED, 0x9C, 0xB3,
    0x7E, 0x51, 0x20, 0x0F, 0x3B, 0x14, 0x65, 0x4A, 0x87, 0xA8, 0xD9, 0xF6,
    0x6C, 0x43, 0x32, 0x1D, 0xD0, 0xFF, 0x8E, 0xA1, 0xE3, 0xCC, 0xBD, 0x92,
    0x5F, 0x70, 0x01, 0x2E, 0xB4, 0x9B, 0xEA, 0xC5, 0x08, 0x27, 0x56, 0x79,
    0x4D, 0x62, 0x13, 0x3C, 0xF1, 0xDE, 0xAF, 0x80, 0x1A, 0x35, 0x44, 0x6B,
    0xA6, 0x89, 0xF8, 0xD7, 0x90, 0xBF, 0xCE, 0xE1, 0x2C, 0x03, 0x72, 0x5D,
    0xC7, 0xE8, 0x99, 0xB6, 0x7B, 0x54, 0x25, 0x0A, 0x3E, 0x11, 0x60, 0x4F,
    0x82, 0xAD, 0xDC, 0xF3, 0x69, 0x46, 0x37, 0x18, 0xD5, 0xFA, 0x8B, 0xA4,
    0x05, 0x2A, 0x5B, 0x74, 0xB9, 0x96, 0xE7, 0xC8, 0x52, 0x7D, 0x0C, 0x23,
    0xEE, 0xC1, 0xB0, 0x9F, 0xAB, 0x84, 0xF5, 0xDA, 0x17, 0x38, 0x49, 0x66,
    0xFC, 0xD3, 0xA2, 0x8D, 0x40, 0x6F, 0x1E, 0x31, 0x76, 0x59, 0x28, 0x07,
    0xCA, 0xE5, 0x94, 0xBB, 0x21, 0x0E, 0x7F, 0x50, 0x9D, 0xB2, 0xC3, 0xEC,
    0xD8, 0xF7, 0x86, 0xA9, 0x64, 0x4B, 0x3A, 0x15, 0x8F, 0xA0, 0xD1, 0xFE,
    0x33, 0x1C, 0x6D, 0x42
};

/* the next CRC-16 register after one byte, for the polynomial 0x1021
 * (CRC-16/CCITT-FALSE, E2E Profile 5): crc = (crc << 8) ^ crc_1021[(crc >> 8) ^ byte] */
static const uint16_t crc_1021[256] = {
    0x0000, 0x1021, 0x2042, 0x3063, 0x4084, 0x50A5, 0x60C6, 0x70E7,
    0x8108, 0x9129, 0xA14A, 0xB16B, 0xC18C, 0xD1AD, 0xE1CE, 0xF1EF,
    0x1231, 0x0210, 0x3273, 0x2252, 0x52B5, 0x4294, 0x72F7, 0x62D6,
    0x9339, 0x8318, 0xB37B, 0xA35A, 0xD3BD, 0xC39C, 0xF3FF, 0xE3DE,
    0x2462, 0x3443, 0x0420, 0x1401, 0x64E6, 0x74C7, 0x44A4, 0x5485,
    0xA56A, 0xB54B, 0x8528, 0x9509, 0xE5EE, 0xF5CF, 0xC5AC, 0xD58D,
    0x3653, 0x2672, 0x1611, 0x0630, 0x76D7, 0x66F6, 0x5695, 0x46B4,
    0xB75B, 0xA77A, 0x9719, 0x8738, 0xF7DF, 0xE7FE, 0xD79D, 0xC7BC,
    0x48C4, 0x58E5, 0x6886, 0x78A7, 0x0840, 0x1861, 0x2802, 0x3823,
    0xC9CC, 0xD9ED, 0xE98E, 0xF9AF, 0x8948, 0x9969, 0xA90A, 0xB92B,
    0x5AF5, 0x4AD4, 0x7AB7, 0x6A96, 0x1A71, 0x0A50, 0x3A33, 0x2A12,
    0xDBFD, 0xCBDC, 0xFBBF, 0xEB9E, 0x9B79, 0x8B58, 0xBB3B, 0xAB1A,
    0x6CA6, 0x7C87, 0x4CE4, 0x5CC5, 0x2C22, 0x3C03, 0x0C60, 0x1C41,
    0xEDAE, 0xFD8F, 0xCDEC, 0xDDCD, 0xAD2A, 0xBD0B, 0x8D68, 0x9D49,
    0x7E97, 0x6EB6, 0x5ED5, 0x4EF4, 0x3E13, 0x2E32, 0x1E51, 0x0E70,
    0xFF9F, 0xEFBE, 0xDFDD, 0xCFFC, 0xBF1B, 0xAF3A, 0x9F59, 0x8F78,
    0x9188, 0x81A9, 0xB1CA, 0xA1EB, 0xD10C, 0xC12D, 0xF14E, 0xE16F,
    0x1080, 0x00A1, 0x30C2, 0x20E3, 0x5004, 0x4025, 0x7046, 0x6067,
    0x83B9, 0x9398, 0xA3FB, 0xB3DA, 0xC33D, 0xD31C, 0xE37F, 0xF35E,
    0x02B1, 0x1290, 0x22F3, 0x32D2, 0x4235, 0x5214, 0x6277, 0x7256,
    0xB5EA, 0xA5CB, 0x95A8, 0x8589, 0xF56E, 0xE54F, 0xD52C, 0xC50D,
    0x34E2, 0x24C3, 0x14A0, 0x0481, 0x7466, 0x6447, 0x5424, 0x4405,
    0xA7DB, 0xB7FA, 0x8799, 0x97B8, 0xE75F, 0xF77E, 0xC71D, 0xD73C,
    0x26D3, 0x36F2, 0x0691, 0x16B0, 0x6657, 0x7676, 0x4615, 0x5634,
    0xD94C, 0xC96D, 0xF90E, 0xE92F, 0x99C8, 0x89E9, 0xB98A, 0xA9AB,
    0x5844, 0x4865, 0x7806, 0x6827, 0x18C0, 0x08E1, 0x3882, 0x28A3,
    0xCB7D, 0xDB5C, 0xEB3F, 0xFB1E, 0x8BF9, 0x9BD8, 0xABBB, 0xBB9A,
    0x4A75, 0x5A54, 0x6A37, 0x7A16, 0x0AF1, 0x1AD0, 0x2AB3, 0x3A92,
    0xFD2E, 0xED0F, 0xDD6C, 0xCD4D, 0xBDAA, 0xAD8B, 0x9DE8, 0x8DC9,
    0x7C26, 0x6C07, 0x5C64, 0x4C45, 0x3CA2, 0x2C83, 0x1CE0, 0x0CC1,
    0xEF1F, 0xFF3E, 0xCF5D, 0xDF7C, 0xAF9B, 0xBFBA, 0x8FD9, 0x9FF8,
    0x6E17, 0x7E36, 0x4E55, 0x5E74, 0x2E93, 0x3EB2, 0x0ED1, 0x1EF0
};

/* the next CRC-32P4 register after one byte (reflected polynomial 0xF4ACFB13,
 * E2E Profile 4): crc = (crc >> 8) ^ crc_p4[(crc ^ byte) & 0xFF] */
static const uint32_t crc_p4[256] = {
    0x00000000u, 0x30850FF5u, 0x610A1FEAu, 0x518F101Fu, 0xC2143FD4u, 0xF2913021u,
    0xA31E203Eu, 0x939B2FCBu, 0x159615F7u, 0x25131A02u, 0x749C0A1Du, 0x441905E8u,
    0xD7822A23u, 0xE70725D6u, 0xB68835C9u, 0x860D3A3Cu, 0x2B2C2BEEu, 0x1BA9241Bu,
    0x4A263404u, 0x7AA33BF1u, 0xE938143Au, 0xD9BD1BCFu, 0x88320BD0u, 0xB8B70425u,
    0x3EBA3E19u, 0x0E3F31ECu, 0x5FB021F3u, 0x6F352E06u, 0xFCAE01CDu, 0xCC2B0E38u,
    0x9DA41E27u, 0xAD2111D2u, 0x565857DCu, 0x66DD5829u, 0x37524836u, 0x07D747C3u,
    0x944C6808u, 0xA4C967FDu, 0xF54677E2u, 0xC5C37817u, 0x43CE422Bu, 0x734B4DDEu,
    0x22C45DC1u, 0x12415234u, 0x81DA7DFFu, 0xB15F720Au, 0xE0D06215u, 0xD0556DE0u,
    0x7D747C32u, 0x4DF173C7u, 0x1C7E63D8u, 0x2CFB6C2Du, 0xBF6043E6u, 0x8FE54C13u,
    0xDE6A5C0Cu, 0xEEEF53F9u, 0x68E269C5u, 0x58676630u, 0x09E8762Fu, 0x396D79DAu,
    0xAAF65611u, 0x9A7359E4u, 0xCBFC49FBu, 0xFB79460Eu, 0xACB0AFB8u, 0x9C35A04Du,
    0xCDBAB052u, 0xFD3FBFA7u, 0x6EA4906Cu, 0x5E219F99u, 0x0FAE8F86u, 0x3F2B8073u,
    0xB926BA4Fu, 0x89A3B5BAu, 0xD82CA5A5u, 0xE8A9AA50u, 0x7B32859Bu, 0x4BB78A6Eu,
    0x1A389A71u, 0x2ABD9584u, 0x879C8456u, 0xB7198BA3u, 0xE6969BBCu, 0xD6139449u,
    0x4588BB82u, 0x750DB477u, 0x2482A468u, 0x1407AB9Du, 0x920A91A1u, 0xA28F9E54u,
    0xF3008E4Bu, 0xC38581BEu, 0x501EAE75u, 0x609BA180u, 0x3114B19Fu, 0x0191BE6Au,
    0xFAE8F864u, 0xCA6DF791u, 0x9BE2E78Eu, 0xAB67E87Bu, 0x38FCC7B0u, 0x0879C845u,
    0x59F6D85Au, 0x6973D7AFu, 0xEF7EED93u, 0xDFFBE266u, 0x8E74F279u, 0xBEF1FD8Cu,
    0x2D6AD247u, 0x1DEFDDB2u, 0x4C60CDADu, 0x7CE5C258u, 0xD1C4D38Au, 0xE141DC7Fu,
    0xB0CECC60u, 0x804BC395u, 0x13D0EC5Eu, 0x2355E3ABu, 0x72DAF3B4u, 0x425FFC41u,
    0xC452C67Du, 0xF4D7C988u, 0xA558D997u, 0x95DDD662u, 0x0646F9A9u, 0x36C3F65Cu,
    0x674CE643u, 0x57C9E9B6u, 0xC8DF352Fu, 0xF85A3ADAu, 0xA9D52AC5u, 0x99502530u,
    0x0ACB0AFBu, 0x3A4E050Eu, 0x6BC11511u, 0x5B441AE4u, 0xDD4920D8u, 0xEDCC2F2Du,
    0xBC433F32u, 0x8CC630C7u, 0x1F5D1F0Cu, 0x2FD810F9u, 0x7E5700E6u, 0x4ED20F13u,
    0xE3F31EC1u, 0xD3761134u, 0x82F9012Bu, 0xB27C0EDEu, 0x21E72115u, 0x11622EE0u,
    0x40ED3EFFu, 0x7068310Au, 0xF6650B36u, 0xC6E004C3u, 0x976F14DCu, 0xA7EA1B29u,
    0x347134E2u, 0x04F43B17u, 0x557B2B08u, 0x65FE24FDu, 0x9E8762F3u, 0xAE026D06u,
    0xFF8D7D19u, 0xCF0872ECu, 0x5C935D27u, 0x6C1652D2u, 0x3D9942CDu, 0x0D1C4D38u,
    0x8B117704u, 0xBB9478F1u, 0xEA1B68EEu, 0xDA9E671Bu, 0x490548D0u, 0x79804725u,
    0x280F573Au, 0x188A58CFu, 0xB5AB491Du, 0x852E46E8u, 0xD4A156F7u, 0xE4245902u,
    0x77BF76C9u, 0x473A793Cu, 0x16B56923u, 0x263066D6u, 0xA03D5CEAu, 0x90B8531Fu,
    0xC1374300u, 0xF1B24CF5u, 0x6229633Eu, 0x52AC6CCBu, 0x03237CD4u, 0x33A67321u,
    0x646F9A97u, 0x54EA9562u, 0x0565857Du, 0x35E08A88u, 0xA67BA543u, 0x96FEAAB6u,
    0xC771BAA9u, 0xF7F4B55Cu, 0x71F98F60u, 0x417C8095u, 0x10F3908Au, 0x20769F7Fu,
    0xB3EDB0B4u, 0x8368BF41u, 0xD2E7AF5Eu, 0xE262A0ABu, 0x4F43B179u, 0x7FC6BE8Cu,
    0x2E49AE93u, 0x1ECCA166u, 0x8D578EADu, 0xBDD28158u, 0xEC5D9147u, 0xDCD89EB2u,
    0x5AD5A48Eu, 0x6A50AB7Bu, 0x3BDFBB64u, 0x0B5AB491u, 0x98C19B5Au, 0xA84494AFu,
    0xF9CB84B0u, 0xC94E8B45u, 0x3237CD4Bu, 0x02B2C2BEu, 0x533DD2A1u, 0x63B8DD54u,
    0xF023F29Fu, 0xC0A6FD6Au, 0x9129ED75u, 0xA1ACE280u, 0x27A1D8BCu, 0x1724D749u,
    0x46ABC756u, 0x762EC8A3u, 0xE5B5E768u, 0xD530E89Du, 0x84BFF882u, 0xB43AF777u,
    0x191BE6A5u, 0x299EE950u, 0x7811F94Fu, 0x4894F6BAu, 0xDB0FD971u, 0xEB8AD684u,
    0xBA05C69Bu, 0x8A80C96Eu, 0x0C8DF352u, 0x3C08FCA7u, 0x6D87ECB8u, 0x5D02E34Du,
    0xCE99CC86u, 0xFE1CC373u, 0xAF93D36Cu, 0x9F16DC99u
};

/* the next CRC-64 register after one byte (ECMA-182 polynomial
 * 0x42F0E1EBA9EA3693 reflected, E2E Profile 7): crc = (crc >> 8) ^
 * crc_64[(crc ^ byte) & 0xFF] */
static const uint64_t crc_64[256] = {
    0x0000000000000000u, 0xB32E4CBE03A75F6Fu, 0xF4843657A840A05Bu,
    0x47AA7AE9ABE7FF34u, 0x7BD0C384FF8F5E33u, 0xC8FE8F3AFC28015Cu,
    0x8F54F5D357CFFE68u, 0x3C7AB96D5468A107u, 0xF7A18709FF1EBC66u,
    0x448FCBB7FCB9E309u, 0x0325B15E575E1C3Du, 0xB00BFDE054F94352u,
    0x8C71448D0091E255u, 0x3F5F08330336BD3Au, 0x78F572DAA8D1420Eu,
    0xCBDB3E64AB761D61u, 0x7D9BA13851336649u, 0xCEB5ED8652943926u,
    0x891F976FF973C612u, 0x3A31DBD1FAD4997Du, 0x064B62BCAEBC387Au,
    0xB5652E02AD1B6715u, 0xF2CF54EB06FC9821u, 0x41E11855055BC74Eu,
    0x8A3A2631AE2DDA2Fu, 0x39146A8FAD8A8540u, 0x7EBE1066066D7A74u,
    0xCD905CD805CA251Bu, 0xF1EAE5B551A2841Cu, 0x42C4A90B5205DB73u,
    0x056ED3E2F9E22447u, 0xB6409F5CFA457B28u, 0xFB374270A266CC92u,
    0x48190ECEA1C193FDu, 0x0FB374270A266CC9u, 0xBC9D3899098133A6u,
    0x80E781F45DE992A1u, 0x33C9CD4A5E4ECDCEu, 0x7463B7A3F5A932FAu,
    0xC74DFB1DF60E6D95u, 0x0C96C5795D7870F4u, 0xBFB889C75EDF2F9Bu,
    0xF812F32EF538D0AFu, 0x4B3CBF90F69F8FC0u, 0x774606FDA2F72EC7u,
    0xC4684A43A15071A8u, 0x83C230AA0AB78E9Cu, 0x30EC7C140910D1F3u,
    0x86ACE348F355AADBu, 0x3582AFF6F0F2F5B4u, 0x7228D51F5B150A80u,
    0xC10699A158B255EFu, 0xFD7C20CC0CDAF4E8u, 0x4E526C720F7DAB87u,
    0x09F8169BA49A54B3u, 0xBAD65A25A73D0BDCu, 0x710D64410C4B16BDu,
    0xC22328FF0FEC49D2u, 0x85895216A40BB6E6u, 0x36A71EA8A7ACE989u,
    0x0ADDA7C5F3C4488Eu, 0xB9F3EB7BF06317E1u, 0xFE5991925B84E8D5u,
    0x4D77DD2C5823B7BAu, 0x64B62BCAEBC387A1u, 0xD7986774E864D8CEu,
    0x90321D9D438327FAu, 0x231C512340247895u, 0x1F66E84E144CD992u,
    0xAC48A4F017EB86FDu, 0xEBE2DE19BC0C79C9u, 0x58CC92A7BFAB26A6u,
    0x9317ACC314DD3BC7u, 0x2039E07D177A64A8u, 0x67939A94BC9D9B9Cu,
    0xD4BDD62ABF3AC4F3u, 0xE8C76F47EB5265F4u, 0x5BE923F9E8F53A9Bu,
    0x1C4359104312C5AFu, 0xAF6D15AE40B59AC0u, 0x192D8AF2BAF0E1E8u,
    0xAA03C64CB957BE87u, 0xEDA9BCA512B041B3u, 0x5E87F01B11171EDCu,
    0x62FD4976457FBFDBu, 0xD1D305C846D8E0B4u, 0x96797F21ED3F1F80u,
    0x2557339FEE9840EFu, 0xEE8C0DFB45EE5D8Eu, 0x5DA24145464902E1u,
    0x1A083BACEDAEFDD5u, 0xA9267712EE09A2BAu, 0x955CCE7FBA6103BDu,
    0x267282C1B9C65CD2u, 0x61D8F8281221A3E6u, 0xD2F6B4961186FC89u,
    0x9F8169BA49A54B33u, 0x2CAF25044A02145Cu, 0x6B055FEDE1E5EB68u,
    0xD82B1353E242B407u, 0xE451AA3EB62A1500u, 0x577FE680B58D4A6Fu,
    0x10D59C691E6AB55Bu, 0xA3FBD0D71DCDEA34u, 0x6820EEB3B6BBF755u,
    0xDB0EA20DB51CA83Au, 0x9CA4D8E41EFB570Eu, 0x2F8A945A1D5C0861u,
    0x13F02D374934A966u, 0xA0DE61894A93F609u, 0xE7741B60E174093Du,
    0x545A57DEE2D35652u, 0xE21AC88218962D7Au, 0x5134843C1B317215u,
    0x169EFED5B0D68D21u, 0xA5B0B26BB371D24Eu, 0x99CA0B06E7197349u,
    0x2AE447B8E4BE2C26u, 0x6D4E3D514F59D312u, 0xDE6071EF4CFE8C7Du,
    0x15BB4F8BE788911Cu, 0xA6950335E42FCE73u, 0xE13F79DC4FC83147u,
    0x521135624C6F6E28u, 0x6E6B8C0F1807CF2Fu, 0xDD45C0B11BA09040u,
    0x9AEFBA58B0476F74u, 0x29C1F6E6B3E0301Bu, 0xC96C5795D7870F42u,
    0x7A421B2BD420502Du, 0x3DE861C27FC7AF19u, 0x8EC62D7C7C60F076u,
    0xB2BC941128085171u, 0x0192D8AF2BAF0E1Eu, 0x4638A2468048F12Au,
    0xF516EEF883EFAE45u, 0x3ECDD09C2899B324u, 0x8DE39C222B3EEC4Bu,
    0xCA49E6CB80D9137Fu, 0x7967AA75837E4C10u, 0x451D1318D716ED17u,
    0xF6335FA6D4B1B278u, 0xB199254F7F564D4Cu, 0x02B769F17CF11223u,
    0xB4F7F6AD86B4690Bu, 0x07D9BA1385133664u, 0x4073C0FA2EF4C950u,
    0xF35D8C442D53963Fu, 0xCF273529793B3738u, 0x7C0979977A9C6857u,
    0x3BA3037ED17B9763u, 0x888D4FC0D2DCC80Cu, 0x435671A479AAD56Du,
    0xF0783D1A7A0D8A02u, 0xB7D247F3D1EA7536u, 0x04FC0B4DD24D2A59u,
    0x3886B22086258B5Eu, 0x8BA8FE9E8582D431u, 0xCC0284772E652B05u,
    0x7F2CC8C92DC2746Au, 0x325B15E575E1C3D0u, 0x8175595B76469CBFu,
    0xC6DF23B2DDA1638Bu, 0x75F16F0CDE063CE4u, 0x498BD6618A6E9DE3u,
    0xFAA59ADF89C9C28Cu, 0xBD0FE036222E3DB8u, 0x0E21AC88218962D7u,
    0xC5FA92EC8AFF7FB6u, 0x76D4DE52895820D9u, 0x317EA4BB22BFDFEDu,
    0x8250E80521188082u, 0xBE2A516875702185u, 0x0D041DD676D77EEAu,
    0x4AAE673FDD3081DEu, 0xF9802B81DE97DEB1u, 0x4FC0B4DD24D2A599u,
    0xFCEEF8632775FAF6u, 0xBB44828A8C9205C2u, 0x086ACE348F355AADu,
    0x34107759DB5DFBAAu, 0x873E3BE7D8FAA4C5u, 0xC094410E731D5BF1u,
    0x73BA0DB070BA049Eu, 0xB86133D4DBCC19FFu, 0x0B4F7F6AD86B4690u,
    0x4CE50583738CB9A4u, 0xFFCB493D702BE6CBu, 0xC3B1F050244347CCu,
    0x709FBCEE27E418A3u, 0x3735C6078C03E797u, 0x841B8AB98FA4B8F8u,
    0xADDA7C5F3C4488E3u, 0x1EF430E13FE3D78Cu, 0x595E4A08940428B8u,
    0xEA7006B697A377D7u, 0xD60ABFDBC3CBD6D0u, 0x6524F365C06C89BFu,
    0x228E898C6B8B768Bu, 0x91A0C532682C29E4u, 0x5A7BFB56C35A3485u,
    0xE955B7E8C0FD6BEAu, 0xAEFFCD016B1A94DEu, 0x1DD181BF68BDCBB1u,
    0x21AB38D23CD56AB6u, 0x9285746C3F7235D9u, 0xD52F0E859495CAEDu,
    0x6601423B97329582u, 0xD041DD676D77EEAAu, 0x636F91D96ED0B1C5u,
    0x24C5EB30C5374EF1u, 0x97EBA78EC690119Eu, 0xAB911EE392F8B099u,
    0x18BF525D915FEFF6u, 0x5F1528B43AB810C2u, 0xEC3B640A391F4FADu,
    0x27E05A6E926952CCu, 0x94CE16D091CE0DA3u, 0xD3646C393A29F297u,
    0x604A2087398EADF8u, 0x5C3099EA6DE60CFFu, 0xEF1ED5546E415390u,
    0xA8B4AFBDC5A6ACA4u, 0x1B9AE303C601F3CBu, 0x56ED3E2F9E224471u,
    0xE5C372919D851B1Eu, 0xA26908783662E42Au, 0x114744C635C5BB45u,
    0x2D3DFDAB61AD1A42u, 0x9E13B115620A452Du, 0xD9B9CBFCC9EDBA19u,
    0x6A978742CA4AE576u, 0xA14CB926613CF817u, 0x1262F598629BA778u,
    0x55C88F71C97C584Cu, 0xE6E6C3CFCADB0723u, 0xDA9C7AA29EB3A624u,
    0x69B2361C9D14F94Bu, 0x2E184CF536F3067Fu, 0x9D36004B35545910u,
    0x2B769F17CF112238u, 0x9858D3A9CCB67D57u, 0xDFF2A94067518263u,
    0x6CDCE5FE64F6DD0Cu, 0x50A65C93309E7C0Bu, 0xE388102D33392364u,
    0xA4226AC498DEDC50u, 0x170C267A9B79833Fu, 0xDCD7181E300F9E5Eu,
    0x6FF954A033A8C131u, 0x28532E49984F3E05u, 0x9B7D62F79BE8616Au,
    0xA707DB9ACF80C06Du, 0x14299724CC279F02u, 0x5383EDCD67C06036u,
    0xE0ADA17364673F59u
};

/* ------------------------------------------------------------------ */
/* CRC                                                                 */
/* ------------------------------------------------------------------ */

uint8_t ct_crc8_j1850(const uint8_t *bytes, size_t n)
{
    uint8_t crc = 0xFFu;
    for (size_t i = 0; i < n; i++) {
        crc = crc_1d[crc ^ bytes[i]];
    }
    return (uint8_t)(crc ^ 0xFFu);
}

uint8_t ct_crc8_h2f(const uint8_t *bytes, size_t n)
{
    uint8_t crc = 0xFFu;
    for (size_t i = 0; i < n; i++) {
        crc = crc_2f[crc ^ bytes[i]];
    }
    return (uint8_t)(crc ^ 0xFFu);
}

uint16_t ct_crc16_ccitt_false(const uint8_t *bytes, size_t n)
{
    uint16_t crc = 0xFFFFu;
    for (size_t i = 0; i < n; i++) {
        crc = (uint16_t)((crc << 8) ^ crc_1021[(crc >> 8) ^ bytes[i]]);
    }
    return crc;
}

uint32_t ct_crc32_p4(const uint8_t *bytes, size_t n)
{
    uint32_t crc = 0xFFFFFFFFu;
    for (size_t i = 0; i < n; i++) {
        crc = (crc >> 8) ^ crc_p4[(crc ^ bytes[i]) & 0xFFu];
    }
    return crc ^ 0xFFFFFFFFu;
}

uint64_t ct_crc64(const uint8_t *bytes, size_t n)
{
    uint64_t crc = ~(uint64_t)0;
    for (size_t i = 0; i < n; i++) {
        crc = (crc >> 8) ^ crc_64[(crc ^ bytes[i]) & 0xFFu];
    }
    return ~crc;
}

/* crc register run over data[0 .. len-1] without data[skip] */
static uint8_t crc_run(const uint8_t *tab, uint8_t crc, const uint8_t *data, int len, int skip)
{
    for (int i = 0; i < len; i++) {
        if (i != skip) {
            crc = tab[crc ^ data[i]];
        }
    }
    return crc;
}

/* ------------------------------------------------------------------ */
/* Bit fields                                                          */
/* ------------------------------------------------------------------ */

static uint64_t field_mask(unsigned length)
{
    return length >= 64u ? ~(uint64_t)0 : (((uint64_t)1 << length) - 1u);
}

/* the width of a field's next piece: the bits left in the byte, at most the
 * bits left of the field */
CT_INLINE unsigned chunk_bits(unsigned in_byte, unsigned left)
{
    return in_byte < left ? in_byte : left;
}

CT_INLINE uint64_t get_bits(const uint8_t *d, const ct_signal *s)
{
    unsigned len = s->length;
    uint64_t v = 0;
    if (((s->start | len) & 7u) == 0u && !s->big_endian) {   /* whole bytes, the common case */
        const uint8_t *p = d + (s->start >> 3);
        for (unsigned k = len >> 3; k-- > 0u;) {
            v = (v << 8) | p[k];
        }
    } else if (!s->big_endian) {
        unsigned pos = s->start;
        unsigned shift = 0;
        while (shift < len) {
            unsigned off = pos & 7u;
            unsigned n = chunk_bits(8u - off, len - shift);
            uint64_t chunk = (uint64_t)((d[pos >> 3] >> off) & ((1u << n) - 1u));
            v |= chunk << shift;
            shift += n;
            pos += n;
        }
    } else {
        unsigned byte = (unsigned)s->start >> 3;
        unsigned top = (unsigned)s->start & 7u;   /* highest bit of the field in this byte */
        unsigned rem = len;
        while (rem > 0u) {
            unsigned n = chunk_bits(top + 1u, rem);
            uint64_t chunk = (uint64_t)((d[byte] >> (top + 1u - n)) & ((1u << n) - 1u));
            v = (v << n) | chunk;
            rem -= n;
            byte++;
            top = 7u;
        }
    }
    return v;
}

CT_INLINE void put_bits(uint8_t *d, const ct_signal *s, uint64_t v)
{
    unsigned len = s->length;
    if (((s->start | len) & 7u) == 0u && !s->big_endian) {
        uint8_t *p = d + (s->start >> 3);
        for (unsigned k = 0; k < (len >> 3); k++) {
            p[k] = (uint8_t)(v >> (8u * k));
        }
    } else if (!s->big_endian) {
        unsigned pos = s->start;
        unsigned shift = 0;
        while (shift < len) {
            unsigned off = pos & 7u;
            unsigned n = chunk_bits(8u - off, len - shift);
            unsigned m = ((1u << n) - 1u) << off;
            unsigned chunk = (unsigned)((v >> shift) & ((1u << n) - 1u)) << off;
            d[pos >> 3] = (uint8_t)((d[pos >> 3] & ~m) | chunk);
            shift += n;
            pos += n;
        }
    } else {
        unsigned byte = (unsigned)s->start >> 3;
        unsigned top = (unsigned)s->start & 7u;
        unsigned rem = len;
        while (rem > 0u) {
            unsigned n = chunk_bits(top + 1u, rem);
            unsigned lo = top + 1u - n;
            unsigned m = ((1u << n) - 1u) << lo;
            unsigned chunk = (unsigned)((v >> (rem - n)) & ((1u << n) - 1u)) << lo;
            d[byte] = (uint8_t)((d[byte] & ~m) | chunk);
            rem -= n;
            byte++;
            top = 7u;
        }
    }
}

/* ------------------------------------------------------------------ */
/* Raw <-> physical                                                    */
/* ------------------------------------------------------------------ */

/* magnitude (hi:lo, 128 bits) to the nearest double, ties to even */
static double u128_to_double(uint64_t hi, uint64_t lo)
{
    if (hi == 0u) {
        return (double)lo;
    }
    unsigned s = 0;                  /* bits of hi */
    for (uint64_t h = hi; h != 0u; h >>= 1) {
        s++;
    }
    /* the top 64 bits, with the bits shifted out kept as a sticky bit in
     * bit 0: far below double's rounding position, so one rounding of
     * the 64-bit value rounds the whole 128-bit one correctly */
    uint64_t top = s == 64u ? hi : ((hi << (64u - s)) | (lo >> s));
    uint64_t below = s == 64u ? lo : (lo << (64u - s));
    if (below != 0u) {
        top |= 1u;
    }
    return ldexp((double)top, (int)s);
}

/* raw (-1)^neg * mag times factor_int plus offset_int, exactly, rounded once
 * (|factor_int|, |offset_int| <= 2^53: the sum stays within 128 bits) */
static double integer_value(const ct_signal *s, int neg, uint64_t mag)
{
    uint64_t f = s->factor_int < 0 ? (uint64_t)0 - (uint64_t)s->factor_int : (uint64_t)s->factor_int;
    /* 64 x 64 -> 128 bit product of the magnitudes */
    uint64_t a0 = mag & 0xFFFFFFFFu, a1 = mag >> 32;
    uint64_t b0 = f & 0xFFFFFFFFu, b1 = f >> 32;
    uint64_t p00 = a0 * b0, p01 = a0 * b1, p10 = a1 * b0, p11 = a1 * b1;
    uint64_t mid = (p00 >> 32) + (p01 & 0xFFFFFFFFu) + (p10 & 0xFFFFFFFFu);
    uint64_t lo = (p00 & 0xFFFFFFFFu) | (mid << 32);
    uint64_t hi = p11 + (p01 >> 32) + (p10 >> 32) + (mid >> 32);
    /* as two's complement, plus the offset sign-extended */
    if (neg != (s->factor_int < 0)) {
        lo = ~lo + 1u;
        hi = ~hi + (lo == 0u ? 1u : 0u);
    }
    uint64_t olo = (uint64_t)s->offset_int;
    uint64_t ohi = s->offset_int < 0 ? ~(uint64_t)0 : 0u;
    uint64_t sum_lo = lo + olo;
    uint64_t sum_hi = hi + ohi + (sum_lo < lo ? 1u : 0u);
    if (sum_hi >> 63) {               /* negative */
        sum_lo = ~sum_lo + 1u;
        sum_hi = ~sum_hi + (sum_lo == 0u ? 1u : 0u);
        return -u128_to_double(sum_hi, sum_lo);
    }
    return u128_to_double(sum_hi, sum_lo);
}

/* the physical value of a signal's raw bits, as cantools decodes it */
CT_INLINE double decode_bits(const ct_signal *s, uint64_t u)
{
    if (s->is_float) {
        double raw;
        if (s->length == 32u) {
            uint32_t w = (uint32_t)u;
            float f;
            memcpy(&f, &w, sizeof f);
            raw = (double)f;
        } else {
            memcpy(&raw, &u, sizeof raw);
        }
        return s->conversion == CT_CONV_IDENTITY ? raw : raw * s->factor + s->offset;
    }
    int neg = 0;
    uint64_t mag = u;
    if (s->is_signed && ((u >> (s->length - 1u)) & 1u)) {
        neg = 1;
        mag = (~u & field_mask(s->length)) + 1u;
    }
    double raw = neg ? -(double)mag : (double)mag;
    switch (s->conversion) {
    case CT_CONV_IDENTITY:
        return raw;
    case CT_CONV_INTEGER:
        if (mag <= s->exact_raw) {    /* every step exact in double */
            return raw * (double)s->factor_int + (double)s->offset_int;
        }
        return integer_value(s, neg, mag);
    case CT_CONV_INT_FACTOR:
        if (mag <= s->exact_raw) {
            return raw * (double)s->factor_int + s->offset;
        }
        return integer_value(s, neg, mag) + s->offset;
    default:
        return raw * s->factor + s->offset;
    }
}

/* the raw bits cantools would pack for physical value v, limited as
 * can_table.h says */
/* the raw bits of physical value v; *limited (if not NULL) counts a value
 * limited to the signal's [minimum, maximum] or bit field (NaN, sent as 0,
 * is not counted: the same rule as can_dbc.table.CodecTable.saturated) */
CT_INLINE uint64_t encode_bits_counted(const ct_signal *s, double v, uint32_t *limited)
{
    int nan = isnan(v);
    if (nan) {
        v = 0.0;
    }
    if (s->limited) {
        if (v < s->minimum) {
            v = s->minimum;
            if (limited != NULL && !nan)
                (*limited)++;
            limited = NULL;           /* counted once */
        } else if (v > s->maximum) {
            v = s->maximum;
            if (limited != NULL)
                (*limited)++;
            limited = NULL;
        }
    }
    double x = (v - s->offset) / s->factor;
    if (s->is_float) {
        if (s->length == 32u) {
            float f = (float)x;
            uint32_t w;
            memcpy(&w, &f, sizeof w);
            return w;
        }
        uint64_t w;
        memcpy(&w, &x, sizeof w);
        return w;
    }
    double r = rint(x);
    if (!(r >= s->raw_min)) {         /* also NaN, which a finite offset and factor never give */
        r = s->raw_min;
        if (limited != NULL && !nan)
            (*limited)++;
    }
    if (r >= s->raw_end) {
        if (limited != NULL)
            (*limited)++;
        return s->is_signed ? field_mask(s->length) >> 1 : field_mask(s->length);
    }
    if (r < 0.0) {                    /* signed field: two's complement */
        uint64_t mag = (uint64_t)(-r);
        return ((~mag) + 1u) & field_mask(s->length);
    }
    return (uint64_t)r;
}

CT_INLINE uint64_t encode_bits(const ct_signal *s, double v)
{
    return encode_bits_counted(s, v, NULL);
}

/* ------------------------------------------------------------------ */
/* Multiplexing                                                        */
/* ------------------------------------------------------------------ */

static int in_ranges(const ct_table *t, const ct_signal *s, double selector)
{
    double v = trunc(selector);
    if (!(v >= -9223372036854775808.0 && v < 9223372036854775808.0)) {
        return 0;
    }
    int64_t k = (int64_t)v;
    for (uint32_t i = 0; i < s->mux_count; i++) {
        const ct_mux_range *r = &t->mux[s->mux_first + i];
        if (k >= r->lo && k <= r->hi) {
            return 1;
        }
    }
    return 0;
}

/* 1 if signal i of the message is selected: by the frame data (values
 * NULL) or by the values to encode (the selector's value as written) */
static int selected(const ct_table *t, const ct_message *m, int i, const uint8_t *data,
                    const double *values)
{
    const ct_signal *sig = t->signals + m->first_signal;
    int hops = 0;
    while (sig[i].mux_signal >= 0) {
        int sel = sig[i].mux_signal;
        if (sel >= (int)m->n_signals || ++hops > (int)m->n_signals) {
            return 0;                 /* a broken table: never loop */
        }
        uint64_t bits = values != NULL ? encode_bits(&sig[sel], values[sel]) : get_bits(data, &sig[sel]);
        if (!in_ranges(t, &sig[i], decode_bits(&sig[sel], bits))) {
            return 0;
        }
        i = sel;
    }
    return 1;
}

/* ------------------------------------------------------------------ */
/* Messages                                                            */
/* ------------------------------------------------------------------ */

static const ct_message *message(const ct_table *t, int msg)
{
    if (t == NULL || msg < 0 || msg >= t->n_messages) {
        return NULL;
    }
    return &t->messages[msg];
}

int ct_find(const ct_table *t, uint32_t id, int extended)
{
    if (t == NULL) {
        return -1;
    }
    for (int i = 0; i < t->n_messages; i++) {
        if (t->messages[i].id == id && (t->messages[i].extended != 0) == (extended != 0)) {
            return i;
        }
    }
    return -1;
}

int ct_encode_counted(const ct_table *t, int msg, const double *values, uint8_t *data,
                      uint32_t *saturated)
{
    const ct_message *m = message(t, msg);
    if (m == NULL) {
        return -1;
    }
    const ct_signal *sig = t->signals + m->first_signal;
    memset(data, 0, m->length);
    for (uint32_t i = 0; i < m->n_signals; i++) {
        if (sig[i].mux_signal >= 0 && !selected(t, m, (int)i, NULL, values)) {
            continue;
        }
        put_bits(data, &sig[i], encode_bits_counted(&sig[i], values[i], saturated));
    }
    return m->length;
}

int ct_encode(const ct_table *t, int msg, const double *values, uint8_t *data)
{
    return ct_encode_counted(t, msg, values, data, NULL);
}

int ct_put_raw(const ct_table *t, int msg, int signal, int64_t raw, uint8_t *data)
{
    const ct_message *m = message(t, msg);
    if (m == NULL || signal < 0 || signal >= (int)m->n_signals) {
        return -1;
    }
    const ct_signal *s = t->signals + m->first_signal + signal;
    put_bits(data, s, (uint64_t)raw & field_mask(s->length));
    return 0;
}

int ct_decode(const ct_table *t, int msg, const uint8_t *data, int len, double *values,
              uint8_t *written)
{
    const ct_message *m = message(t, msg);
    if (m == NULL || len != (int)m->length) {
        return -1;
    }
    const ct_signal *sig = t->signals + m->first_signal;
    int n = 0;
    for (uint32_t i = 0; i < m->n_signals; i++) {
        int on = sig[i].mux_signal < 0 || selected(t, m, (int)i, data, NULL);
        if (on) {
            values[i] = decode_bits(&sig[i], get_bits(data, &sig[i]));
            n++;
        }
        if (written != NULL) {
            written[i] = (uint8_t)on;
        }
    }
    return n;
}

/* the checksum byte of a frame of message m with counter value counter */
static uint8_t checksum(const ct_message *m, const uint8_t *data, int counter)
{
    int len = m->length;
    int skip = m->crc_byte;
    uint8_t crc;
    switch (m->protection) {
    case CT_PROT_DCT:
        crc = crc_1d[0xFFu ^ (uint8_t)(m->id & 0xFFu)];
        crc = crc_1d[crc ^ (uint8_t)((m->id >> 8) & 0xFFu)];
        return (uint8_t)(crc_run(crc_1d, crc, data, len, skip) ^ 0xFFu);
    case CT_PROT_P1: {
        uint8_t lo = (uint8_t)(m->data_id & 0xFFu), hi = (uint8_t)(m->data_id >> 8);
        crc = 0x00u;
        switch (m->data_id_mode) {
        case CT_P1_BOTH:
            crc = crc_1d[crc ^ lo];
            crc = crc_1d[crc ^ hi];
            break;
        case CT_P1_ALT:
            crc = crc_1d[crc ^ ((counter & 1) ? hi : lo)];
            break;
        case CT_P1_LOW:
            crc = crc_1d[crc ^ lo];
            break;
        default:                      /* CT_P1_NIBBLE: the high byte counts as 0 */
            crc = crc_1d[crc ^ lo];
            crc = crc_1d[crc];
            break;
        }
        return crc_run(crc_1d, crc, data, len, skip);
    }
    case CT_PROT_P2:
        crc = crc_run(crc_2f, 0xFFu, data, len, skip);
        crc = crc_2f[crc ^ m->data_id_list[counter & 0x0F]];
        return (uint8_t)(crc ^ 0xFFu);
    case CT_PROT_XOR:
        crc = 0x00u;
        for (int i = 0; i < len; i++) {
            if (i != skip) {
                crc ^= data[i];
            }
        }
        return crc;
    default:
        return 0u;
    }
}

/* Profile 5's CRC of a frame of message m (its header at crc_byte) */
static uint16_t p5_crc(const ct_message *m, const uint8_t *data)
{
    int h = m->crc_byte;
    uint16_t crc = 0xFFFFu;
    for (int i = 0; i < (int)m->length; i++) {
        if (i != h && i != h + 1) {
            crc = (uint16_t)((crc << 8) ^ crc_1021[(crc >> 8) ^ data[i]]);
        }
    }
    crc = (uint16_t)((crc << 8) ^ crc_1021[(crc >> 8) ^ (uint8_t)(m->data_id & 0xFFu)]);
    crc = (uint16_t)((crc << 8) ^ crc_1021[(crc >> 8) ^ (uint8_t)(m->data_id >> 8)]);
    return crc;
}

/* 1 if message m is protected by Profile 5 and its header fits the frame */
static int is_p5(const ct_message *m)
{
    return m->protection == CT_PROT_P5 && m->crc_byte >= 0 && m->crc_byte + 3 <= (int)m->length;
}

/* 1 if message m is protected by Profile 4 and its header fits the frame */
static int is_p4(const ct_message *m)
{
    return m->protection == CT_PROT_P4 && m->crc_byte >= 0 && m->crc_byte + 12 <= (int)m->length;
}

/* 1 if message m is protected by Profile 7 and its header fits the frame */
static int is_p7(const ct_message *m)
{
    return m->protection == CT_PROT_P7 && m->crc_byte >= 0 && m->crc_byte + 20 <= (int)m->length;
}

static uint32_t p4_data_id(const ct_message *m)
{
    return (uint32_t)m->data_id_list[0] | ((uint32_t)m->data_id_list[1] << 8)
        | ((uint32_t)m->data_id_list[2] << 16) | ((uint32_t)m->data_id_list[3] << 24);
}

static void put_be(uint8_t *p, uint32_t v, int n)
{
    for (int i = n - 1; i >= 0; i--) {
        p[i] = (uint8_t)(v & 0xFFu);
        v >>= 8;
    }
}

static uint32_t get_be(const uint8_t *p, int n)
{
    uint32_t v = 0;
    for (int i = 0; i < n; i++) {
        v = (v << 8) | p[i];
    }
    return v;
}

/* Profile 7's CRC of a frame of message m (its header at crc_byte): every
 * byte but the CRC's eight */
static uint64_t p7_crc(const ct_message *m, const uint8_t *data)
{
    int h = m->crc_byte;
    uint64_t crc = ~(uint64_t)0;
    for (int i = 0; i < (int)m->length; i++) {
        if (i < h || i >= h + 8) {
            crc = (crc >> 8) ^ crc_64[(crc ^ data[i]) & 0xFFu];
        }
    }
    return ~crc;
}

/* Profile 4's CRC of a frame of message m (its header at crc_byte): every
 * byte but the CRC's four */
static uint32_t p4_crc(const ct_message *m, const uint8_t *data)
{
    int h = m->crc_byte;
    uint32_t crc = 0xFFFFFFFFu;
    for (int i = 0; i < (int)m->length; i++) {
        if (i < h + 8 || i >= h + 12) {
            crc = (crc >> 8) ^ crc_p4[(crc ^ data[i]) & 0xFFu];
        }
    }
    return crc ^ 0xFFFFFFFFu;
}

static int has_checksum(const ct_message *m)
{
    return m->crc_byte >= 0 && m->crc_byte < (int)m->length
        && (m->protection == CT_PROT_DCT || m->protection == CT_PROT_P1
            || m->protection == CT_PROT_P2 || m->protection == CT_PROT_XOR);
}

int ct_protect(const ct_table *t, int msg, uint8_t *data, uint32_t counter)
{
    const ct_message *m = message(t, msg);
    if (m == NULL) {
        return -1;
    }
    const ct_signal *sig = t->signals + m->first_signal;
    int c = 0;
    if (is_p7(m)) {
        uint8_t *h = data + m->crc_byte;
        put_be(h + 8, m->length, 4);
        put_be(h + 12, counter, 4);
        put_be(h + 16, p4_data_id(m), 4);
        uint64_t crc = p7_crc(m, data);
        put_be(h, (uint32_t)(crc >> 32), 4);
        put_be(h + 4, (uint32_t)(crc & 0xFFFFFFFFu), 4);
        return (int)(counter & 0x7FFFFFFFu);
    }
    if (is_p4(m)) {
        uint8_t *h = data + m->crc_byte;
        c = (int)(counter & 0xFFFFu);
        put_be(h, m->length, 2);
        put_be(h + 2, (uint32_t)c, 2);
        put_be(h + 4, p4_data_id(m), 4);
        put_be(h + 8, p4_crc(m, data), 4);
        return c;
    }
    if (is_p5(m)) {
        c = (int)(counter & 0xFFu);
        data[m->crc_byte + 2] = (uint8_t)c;
        uint16_t crc = p5_crc(m, data);
        data[m->crc_byte] = (uint8_t)(crc & 0xFFu);
        data[m->crc_byte + 1] = (uint8_t)(crc >> 8);
        return c;
    }
    if (m->counter_signal >= 0 && m->counter_modulus > 0u) {
        c = (int)(counter % m->counter_modulus);
        put_bits(data, &sig[m->counter_signal], (uint64_t)c);
    }
    if (m->protection == CT_PROT_P1 && m->data_id_mode == CT_P1_NIBBLE && m->nibble_signal >= 0) {
        put_bits(data, &sig[m->nibble_signal], (uint64_t)((m->data_id >> 8) & 0x0Fu));
    }
    if (has_checksum(m)) {
        data[m->crc_byte] = checksum(m, data, c);
    }
    return c;
}

int ct_check(const ct_table *t, int msg, const uint8_t *data, int len, ct_rx_state *state)
{
    const ct_message *m = message(t, msg);
    if (m == NULL) {
        return CT_RX_UNKNOWN_ID;
    }
    if (len != (int)m->length) {
        return CT_RX_BAD_LENGTH;
    }
    const ct_signal *sig = t->signals + m->first_signal;
    int c = -1;
    if (is_p7(m)) {
        const uint8_t *h = data + m->crc_byte;
        uint64_t crc = p7_crc(m, data);
        if (get_be(h + 8, 4) != m->length || get_be(h + 16, 4) != p4_data_id(m)
            || get_be(h, 4) != (uint32_t)(crc >> 32) || get_be(h + 4, 4) != (uint32_t)(crc & 0xFFFFFFFFu)) {
            return CT_RX_BAD_CRC;
        }
        /* a 32-bit counter: compared modulo 2^32; the state holds its bits
         * (0xFFFFFFFF reads as -1, "no frame yet": the next one starts afresh) */
        uint32_t c32 = get_be(h + 12, 4);
        if (state != NULL) {
            if (state->last_counter != -1) {
                uint32_t step = c32 - (uint32_t)state->last_counter;
                if (step == 0u || step > m->max_delta_counter) {
                    return CT_RX_BAD_COUNTER;
                }
            }
            state->last_counter = (int32_t)c32;
        }
        return CT_RX_OK;
    }
    if (is_p4(m)) {
        const uint8_t *h = data + m->crc_byte;
        if (get_be(h, 2) != m->length || get_be(h + 4, 4) != p4_data_id(m)
            || get_be(h + 8, 4) != p4_crc(m, data)) {
            return CT_RX_BAD_CRC;
        }
        c = (int)get_be(h + 2, 2);
    } else if (is_p5(m)) {
        uint16_t crc = p5_crc(m, data);
        if (data[m->crc_byte] != (uint8_t)(crc & 0xFFu) || data[m->crc_byte + 1] != (uint8_t)(crc >> 8)) {
            return CT_RX_BAD_CRC;
        }
        c = data[m->crc_byte + 2];
    } else if (m->counter_signal >= 0 && m->counter_modulus > 0u) {
        c = (int)get_bits(data, &sig[m->counter_signal]);
    }
    if (has_checksum(m)) {
        if (data[m->crc_byte] != checksum(m, data, c < 0 ? 0 : c)) {
            return CT_RX_BAD_CRC;
        }
        if (m->protection == CT_PROT_P1 && m->data_id_mode == CT_P1_NIBBLE && m->nibble_signal >= 0
            && get_bits(data, &sig[m->nibble_signal]) != (uint64_t)((m->data_id >> 8) & 0x0Fu)) {
            return CT_RX_BAD_CRC;
        }
    }
    if (c >= 0) {
        int mod = (int)m->counter_modulus;
        if (c >= mod) {
            return CT_RX_BAD_COUNTER;
        }
        if (state != NULL) {
            if (state->last_counter >= 0) {
                int step = ((c - state->last_counter) % mod + mod) % mod;
                if (step == 0 || step > (int)m->max_delta_counter) {
                    return CT_RX_BAD_COUNTER;
                }
            }
            state->last_counter = c;
        }
    }
    return CT_RX_OK;
}

/* ------------------------------------------------------------------ */
/* Benchmark                                                           */
/* ------------------------------------------------------------------ */

#define BENCH_FRAMES 16

/* what the timed loop computes goes here, so none of it can be optimised away */
static volatile unsigned bench_sink;

double ct_bench_tick(const ct_table *t, const int32_t *tx, int32_t n_tx, const double *tx_values,
                     const int32_t *rx, int32_t n_rx, const double *rx_values, double *rx_out,
                     int64_t iterations, int64_t *accepted)
{
    uint8_t frames[CT_BENCH_MAX_RX][BENCH_FRAMES][CT_MAX_LENGTH];
    const double *rx_in[CT_BENCH_MAX_RX];
    double *rx_dst[CT_BENCH_MAX_RX];
    const double *tx_in[64];
    int n_frames[CT_BENCH_MAX_RX];
    ct_rx_state states[CT_BENCH_MAX_RX];
    uint8_t out[CT_MAX_LENGTH];
    struct timespec t0, t1;

    if (t == NULL || n_tx < 0 || n_tx > 64 || n_rx < 0 || n_rx > CT_BENCH_MAX_RX || iterations < 1) {
        return -1.0;
    }
    size_t k = 0;
    for (int i = 0; i < n_tx; i++) {
        const ct_message *m = message(t, tx[i]);
        if (m == NULL) {
            return -1.0;
        }
        tx_in[i] = tx_values + k;
        k += m->n_signals;
    }
    k = 0;
    for (int j = 0; j < n_rx; j++) {
        const ct_message *m = message(t, rx[j]);
        if (m == NULL) {
            return -1.0;
        }
        rx_in[j] = rx_values + k;
        rx_dst[j] = rx_out + k;
        k += m->n_signals;
        n_frames[j] = (m->counter_modulus > 0u && m->counter_modulus < BENCH_FRAMES)
            ? (int)m->counter_modulus : BENCH_FRAMES;
        for (int f = 0; f < n_frames[j]; f++) {
            ct_encode(t, rx[j], rx_in[j], frames[j][f]);
            ct_protect(t, rx[j], frames[j][f], (uint32_t)f);
        }
        states[j].last_counter = -1;
    }

    unsigned sink = 0;
    int64_t ok = 0;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    for (int64_t it = 0; it < iterations; it++) {
        for (int i = 0; i < n_tx; i++) {
            ct_encode(t, tx[i], tx_in[i], out);
            ct_protect(t, tx[i], out, (uint32_t)it);
            sink += out[0];
        }
        for (int j = 0; j < n_rx; j++) {
            const ct_message *m = &t->messages[rx[j]];
            const uint8_t *f = frames[j][it % n_frames[j]];
            if (it % n_frames[j] == 0 && (uint32_t)n_frames[j] < m->counter_modulus) {
                /* the frames' counters do not run round the counter's whole range
                 * (an 8-bit counter, P5): start its sequence again */
                states[j].last_counter = -1;
            }
            if (ct_check(t, rx[j], f, m->length, &states[j]) == CT_RX_OK) {
                ct_decode(t, rx[j], f, m->length, rx_dst[j], NULL);
                ok++;
            }
        }
    }
    clock_gettime(CLOCK_MONOTONIC, &t1);
    bench_sink = sink;
    if (accepted != NULL) {
        *accepted = ok;
    }
    double ns = (double)(t1.tv_sec - t0.tv_sec) * 1e9 + (double)(t1.tv_nsec - t0.tv_nsec);
    return ns / (double)iterations;
}
