/*
 * test_vectors.c - check the C decoder/encoder against the golden vectors.
 *
 *   test_vectors tests/vectors/contact.hex tests/vectors/status.hex ...
 *
 * Every announced vector is fed byte by byte to a fresh decoder: "expect=frame" must give
 * exactly one frame with the announced header and fields (CONTACT/STATUS/ACK decoded and
 * compared field by field; commands re-encoded with the C encoders and compared byte for
 * byte), any other "expect=KIND" exactly one error of that kind and no frame.
 * Prints "N passed, M failed"; exit status 1 on any failure.
 */
#define _POSIX_C_SOURCE 200809L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "optitac_proto.h"

#define MAX_KEYS 32
#define LINE_MAX_LEN 4096

typedef struct {
    char name[64];
    char expect[16];
    char keys[MAX_KEYS][32];
    long vals[MAX_KEYS];
    int nkeys;
} vec_t;

static int failures;
static int passes;

static int fail(const vec_t *v, const char *what)
{
    fprintf(stderr, "FAIL %s: %s\n", v->name, what);
    failures++;
    return 0;
}

static int has(const vec_t *v, const char *key, long *out)
{
    int i;
    for (i = 0; i < v->nkeys; i++)
        if (strcmp(v->keys[i], key) == 0) {
            if (out)
                *out = v->vals[i];
            return 1;
        }
    return 0;
}

static long key(const vec_t *v, const char *k)
{
    long val = 0;
    if (!has(v, k, &val)) {
        fprintf(stderr, "vector %s lacks key %s\n", v->name, k);
        exit(2);
    }
    return val;
}

/* "# name: expect=frame k=v ... -- text" */
static int parse_announce(const char *line, vec_t *v)
{
    const char *p = line + 1, *colon, *end;
    char buf[LINE_MAX_LEN];
    char *tok, *save = NULL;
    while (*p == ' ')
        p++;
    colon = strchr(p, ':');
    if (colon == NULL || strstr(line, "expect=") == NULL)
        return 0;
    memset(v, 0, sizeof *v);
    if ((size_t)(colon - p) >= sizeof v->name)
        return 0;
    memcpy(v->name, p, (size_t)(colon - p));
    end = strstr(colon, " -- ");
    if (end == NULL)
        end = colon + strlen(colon);
    if ((size_t)(end - colon) >= sizeof buf)
        return 0;
    memcpy(buf, colon + 1, (size_t)(end - colon - 1));
    buf[end - colon - 1] = '\0';
    for (tok = strtok_r(buf, " \t\r\n", &save); tok; tok = strtok_r(NULL, " \t\r\n", &save)) {
        char *eq = strchr(tok, '=');
        if (eq == NULL)
            continue;
        *eq = '\0';
        if (strcmp(tok, "expect") == 0) {
            strncpy(v->expect, eq + 1, sizeof v->expect - 1);
        } else if (v->nkeys < MAX_KEYS) {
            strncpy(v->keys[v->nkeys], tok, sizeof v->keys[0] - 1);
            v->vals[v->nkeys] = strtol(eq + 1, NULL, 0);
            v->nkeys++;
        }
    }
    return 1;
}

static size_t parse_hex(const char *s, uint8_t *out, size_t cap)
{
    size_t n = 0;
    unsigned int byte;
    while (s[0] && s[1] && s[0] != '\n' && s[0] != '\r' && n < cap) {
        if (sscanf(s, "%2x", &byte) != 1)
            break;
        out[n++] = (uint8_t)byte;
        s += 2;
    }
    return n;
}

#define CHECK(cond, what)           \
    do {                            \
        if (!(cond))                \
            return fail(v, (what)); \
    } while (0)

static int check_fields(const vec_t *v, const optitac_frame_t *f, const uint8_t *wire, size_t wire_len)
{
    long t = key(v, "type");
    CHECK(f->type == t, "type");
    CHECK(f->seq == key(v, "seq"), "seq");
    CHECK((long)f->t_us == key(v, "t_us"), "t_us");
    CHECK(f->payload_len == key(v, "payload_len"), "payload_len");
    if (t == OPTITAC_T_CONTACT && f->payload_len == OPTITAC_CONTACT_PAYLOAD) {
        optitac_contact_t c;
        CHECK(optitac_decode_contact(f, &c) == 0, "decode_contact");
        CHECK(c.sensor_id == key(v, "sensor_id"), "sensor_id");
        CHECK(c.flags == key(v, "flags"), "flags");
        CHECK(c.x == key(v, "x"), "x");
        CHECK(c.y == key(v, "y"), "y");
        CHECK(c.major == key(v, "major"), "major");
        CHECK(c.minor == key(v, "minor"), "minor");
        CHECK(c.angle == key(v, "angle"), "angle");
        CHECK(c.strength == key(v, "strength"), "strength");
        CHECK(c.shape == key(v, "shape"), "shape");
        CHECK(c.confidence == key(v, "confidence"), "confidence");
        CHECK(c.age_us == key(v, "age_us"), "age_us");
    } else if (t == OPTITAC_T_CONTACT) {
        optitac_contact_t c;
        CHECK(optitac_decode_contact(f, &c) != 0, "decode_contact must reject a wrong length");
    } else if (t == OPTITAC_T_STATUS) {
        optitac_status_t s;
        CHECK(optitac_decode_status(f, &s) == 0, "decode_status");
        CHECK(s.sensor_id == key(v, "sensor_id"), "sensor_id");
        CHECK(s.state == key(v, "state"), "state");
        CHECK(s.fps_x10 == key(v, "fps_x10"), "fps_x10");
        CHECK((long)s.frames_dropped == key(v, "frames_dropped"), "frames_dropped");
        CHECK((long)s.camera_errors == key(v, "camera_errors"), "camera_errors");
        CHECK((long)s.link_errors == key(v, "link_errors"), "link_errors");
        CHECK(s.cpu_temp_c_x10 == key(v, "cpu_temp_c_x10"), "cpu_temp_c_x10");
        CHECK((long)s.calibration_id == key(v, "calibration_id"), "calibration_id");
    } else if (t == OPTITAC_T_ACK) {
        optitac_ack_t a;
        CHECK(optitac_decode_ack(f, &a) == 0, "decode_ack");
        CHECK(a.seq_acked == key(v, "seq_acked"), "seq_acked");
        CHECK(a.result == key(v, "result"), "result");
    } else if (t >= OPTITAC_T_PING && t <= OPTITAC_T_SET_THRESHOLD) {
        uint8_t enc[OPTITAC_MAX_WIRE];
        size_t n = 0;
        int encodable = 1;
        uint16_t seq = (uint16_t)key(v, "seq");
        uint32_t t_us = (uint32_t)key(v, "t_us");
        if (t == OPTITAC_T_PING && f->payload_len == 0)
            n = optitac_encode_ping(seq, t_us, enc, sizeof enc);
        else if (t == OPTITAC_T_TARE && f->payload_len == 0)
            n = optitac_encode_tare(seq, t_us, enc, sizeof enc);
        else if (t == OPTITAC_T_STREAM && f->payload_len == 2)
            n = optitac_encode_stream(seq, t_us, (uint8_t)key(v, "on"), (uint8_t)key(v, "rate_divider"),
                                      enc, sizeof enc);
        else if (t == OPTITAC_T_SET_THRESHOLD && f->payload_len == 2)
            n = optitac_encode_set_threshold(seq, t_us, (uint16_t)key(v, "threshold"), enc, sizeof enc);
        else
            encodable = 0; /* a wrong-length command: only the Python side builds those */
        if (encodable) {
            CHECK(n == wire_len, "encoded command length");
            CHECK(memcmp(enc, wire, n) == 0, "encoded command bytes");
        }
    }
    return 1;
}

static void run_vector(const vec_t *v, const uint8_t *wire, size_t n)
{
    optitac_decoder_t d;
    optitac_frame_t f, got;
    size_t i;
    int frames = 0;
    int ok = 1;
    optitac_decoder_init(&d);
    memset(&got, 0, sizeof got);
    for (i = 0; i < n; i++) {
        if (optitac_decoder_feed(&d, wire[i], &f) == OPTITAC_FEED_FRAME) {
            frames++;
            if (frames == 1) {
                ok = check_fields(v, &f, wire, n); /* payload valid until the next feed */
                got = f;
            }
        }
    }
    (void)got;
    if (!ok)
        return;
    if (strcmp(v->expect, "frame") == 0) {
        if (frames != 1 || d.counters.frames != 1) {
            fail(v, "expected exactly one frame");
            return;
        }
    } else {
        const optitac_counters_t *c = &d.counters;
        uint32_t want_cobs = strcmp(v->expect, "cobs") == 0, want_len = strcmp(v->expect, "length") == 0,
                 want_crc = strcmp(v->expect, "crc") == 0, want_ver = strcmp(v->expect, "version") == 0,
                 want_ovf = strcmp(v->expect, "overflow") == 0;
        if (want_cobs + want_len + want_crc + want_ver + want_ovf != 1) {
            fail(v, "unknown expect kind");
            return;
        }
        if (frames != 0 || c->frames != 0 || c->cobs != want_cobs || c->length != want_len ||
            c->crc != want_crc || c->version != want_ver || c->overflow != want_ovf) {
            fail(v, "wrong error counters");
            return;
        }
    }
    passes++;
}

int main(int argc, char **argv)
{
    int i;
    static const uint8_t check[] = "123456789";
    if (optitac_crc16(check, 9) != 0x29B1u) {
        fprintf(stderr, "FAIL crc16 check value\n");
        failures++;
    } else {
        passes++;
    }
    if (argc < 2) {
        fprintf(stderr, "usage: %s VECTORS.hex...\n", argv[0]);
        return 2;
    }
    for (i = 1; i < argc; i++) {
        char line[LINE_MAX_LEN];
        vec_t v;
        int pending = 0;
        FILE *fp = fopen(argv[i], "r");
        if (fp == NULL) {
            perror(argv[i]);
            return 2;
        }
        while (fgets(line, sizeof line, fp) != NULL) {
            if (line[0] == '#') {
                if (parse_announce(line, &v))
                    pending = 1;
            } else if (pending) {
                uint8_t wire[LINE_MAX_LEN / 2];
                size_t n = parse_hex(line, wire, sizeof wire);
                run_vector(&v, wire, n);
                pending = 0;
            }
        }
        fclose(fp);
    }
    printf("%d passed, %d failed\n", passes, failures);
    return failures ? 1 : 0;
}
