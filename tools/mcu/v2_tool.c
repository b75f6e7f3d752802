/*
 * v2_tool.c - the C side of protocol v2's cross-checks (tests/test_protocol_v2_c.py).
 *
 *   v2_tool decode < hex lines    each line one wire frame (hex, delimiter included), fed to a
 *                                 fresh decoder; prints what the C decoders make of it:
 *                                 "contact2 k=v ...", "release k=v ...", "motion k=v ...", "set_protocol k=v ...",
 *                                 "frame type=T ..." for other types, or "error KIND"
 *   v2_tool encode < field lines  "contact2 SEQ T_US sensor_id flags frame index n_contacts contact_id
 *                                 shape x y major minor angle strength depth force confidence age_us",
 *                                 "release SEQ T_US sensor_id contact_id frame touch_frame",
 *                                 "motion SEQ T_US sensor_id flags frame index contact_id vx vy slide_frame
 *                                 vibration" or
 *                                 "set_protocol SEQ T_US version"; prints each wire frame in hex
 */
#define _POSIX_C_SOURCE 200809L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "optitac_proto_v2.h"

static int decode_line(const char *s)
{
    optitac_decoder_t d;
    optitac_frame_t f;
    unsigned int byte;
    int got = 0;
    optitac_decoder_init(&d);
    while (s[0] && s[1] && sscanf(s, "%2x", &byte) == 1) {
        if (optitac_decoder_feed(&d, (uint8_t)byte, &f) == OPTITAC_FEED_FRAME && !got) {
            optitac_contact2_t c;
            optitac_release_t r;
            optitac_motion_t m;
            got = 1;
            if (optitac_decode_contact2(&f, &c) == 0)
                printf("contact2 seq=%u t_us=%lu sensor_id=%u flags=%u frame=%u index=%u n_contacts=%u "
                       "contact_id=%u shape=%u x=%d y=%d major=%u minor=%u angle=%d strength=%u depth=%u "
                       "force=%u confidence=%u age_us=%u\n",
                       f.seq, (unsigned long)f.t_us, c.sensor_id, c.flags, c.frame, c.index, c.n_contacts,
                       c.contact_id, c.shape, c.x, c.y, c.major, c.minor, c.angle, c.strength, c.depth, c.force,
                       c.confidence, c.age_us);
            else if (optitac_decode_release(&f, &r) == 0)
                printf("release seq=%u t_us=%lu sensor_id=%u contact_id=%u frame=%u touch_frame=%u\n", f.seq,
                       (unsigned long)f.t_us, r.sensor_id, r.contact_id, r.frame, r.touch_frame);
            else if (optitac_decode_motion(&f, &m) == 0)
                printf("motion seq=%u t_us=%lu sensor_id=%u flags=%u frame=%u index=%u contact_id=%u vx=%d vy=%d "
                       "slide_frame=%u vibration=%u\n", f.seq, (unsigned long)f.t_us, m.sensor_id, m.flags, m.frame,
                       m.index, m.contact_id, m.vx, m.vy, m.slide_frame, m.vibration);
            else if (f.type == OPTITAC_T_SET_PROTOCOL && f.payload_len == 1u)
                printf("set_protocol seq=%u t_us=%lu version=%u\n", f.seq, (unsigned long)f.t_us, f.payload[0]);
            else
                printf("frame type=%u seq=%u t_us=%lu payload_len=%u\n", f.type, f.seq, (unsigned long)f.t_us,
                       f.payload_len);
        }
        s += 2;
    }
    if (!got) {
        const optitac_counters_t *c = &d.counters;
        printf("error %s\n", c->cobs ? "cobs" : c->length ? "length" : c->crc ? "crc" : c->version ? "version"
                             : c->overflow ? "overflow" : "none");
    }
    return 0;
}

static void print_hex(const uint8_t *p, size_t n)
{
    size_t i;
    if (n == 0u) {
        printf("encode-error\n");
        return;
    }
    for (i = 0; i < n; i++)
        printf("%02x", p[i]);
    printf("\n");
}

static int encode_line(const char *s)
{
    uint8_t out[OPTITAC_MAX_WIRE];
    long v[20];
    char kind[32];
    int n = 0, used = 0;
    const char *p;
    if (sscanf(s, "%31s%n", kind, &used) != 1)
        return 1;
    p = s + used;
    while (n < 20 && sscanf(p, "%ld%n", &v[n], &used) == 1) {
        p += used;
        n++;
    }
    if (strcmp(kind, "contact2") == 0 && n == 19) {
        optitac_contact2_t c;
        c.sensor_id = (uint8_t)v[2];
        c.flags = (uint8_t)v[3];
        c.frame = (uint16_t)v[4];
        c.index = (uint8_t)v[5];
        c.n_contacts = (uint8_t)v[6];
        c.contact_id = (uint8_t)v[7];
        c.shape = (uint8_t)v[8];
        c.x = (int16_t)v[9];
        c.y = (int16_t)v[10];
        c.major = (uint16_t)v[11];
        c.minor = (uint16_t)v[12];
        c.angle = (int16_t)v[13];
        c.strength = (uint16_t)v[14];
        c.depth = (uint16_t)v[15];
        c.force = (uint16_t)v[16];
        c.confidence = (uint8_t)v[17];
        c.age_us = (uint16_t)v[18];
        print_hex(out, optitac_encode_contact2((uint16_t)v[0], (uint32_t)v[1], &c, out, sizeof out));
    } else if (strcmp(kind, "release") == 0 && n == 6) {
        optitac_release_t r;
        r.sensor_id = (uint8_t)v[2];
        r.contact_id = (uint8_t)v[3];
        r.frame = (uint16_t)v[4];
        r.touch_frame = (uint16_t)v[5];
        print_hex(out, optitac_encode_release((uint16_t)v[0], (uint32_t)v[1], &r, out, sizeof out));
    } else if (strcmp(kind, "motion") == 0 && n == 11) {
        optitac_motion_t m;
        m.sensor_id = (uint8_t)v[2];
        m.flags = (uint8_t)v[3];
        m.frame = (uint16_t)v[4];
        m.index = (uint8_t)v[5];
        m.contact_id = (uint8_t)v[6];
        m.vx = (int16_t)v[7];
        m.vy = (int16_t)v[8];
        m.slide_frame = (uint16_t)v[9];
        m.vibration = (uint16_t)v[10];
        print_hex(out, optitac_encode_motion((uint16_t)v[0], (uint32_t)v[1], &m, out, sizeof out));
    } else if (strcmp(kind, "set_protocol") == 0 && n == 3) {
        print_hex(out, optitac_encode_set_protocol((uint16_t)v[0], (uint32_t)v[1], (uint8_t)v[2], out, sizeof out));
    } else {
        fprintf(stderr, "bad line: %s", s);
        return 1;
    }
    return 0;
}

int main(int argc, char **argv)
{
    char line[4096];
    int rc = 0;
    if (argc != 2 || (strcmp(argv[1], "decode") != 0 && strcmp(argv[1], "encode") != 0)) {
        fprintf(stderr, "usage: %s decode|encode < lines\n", argv[0]);
        return 2;
    }
    while (fgets(line, sizeof line, stdin) != NULL) {
        if (line[0] == '\n' || line[0] == '#')
            continue;
        rc |= strcmp(argv[1], "decode") == 0 ? decode_line(line) : encode_line(line);
    }
    return rc;
}
