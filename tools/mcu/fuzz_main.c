/*
 * fuzz_main.c - feed arbitrary bytes to the C decoder and print what it accepts.
 *
 *   optitac_fuzz [-r] [FILE]      (FILE default: stdin)
 *
 * Stream mode: the whole input goes through one decoder.
 *   F <type> <seq> <t_us> <payload hex or -> <typed>   per accepted frame
 *   C <frames> <cobs> <length> <crc> <version> <overflow>   at the end
 * Record mode (-r): the input is records "u32 little-endian length | bytes", each fed
 * to a fresh decoder; lines are prefixed with the record index ("F 12 ..." / "C 12 ...").
 * <typed> is 1 when the CONTACT/STATUS/ACK decoder accepts the payload, 0 when it
 * rejects it, - for other types. Never crashes (run it under ASan/UBSan).
 */
#define _POSIX_C_SOURCE 200809L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "optitac_proto.h"

static void print_frame(long rec, const optitac_frame_t *f)
{
    uint8_t i;
    const char *typed = "-";
    if (rec >= 0)
        printf("F %ld ", rec);
    else
        printf("F ");
    printf("%u %u %lu ", (unsigned)f->type, (unsigned)f->seq, (unsigned long)f->t_us);
    if (f->payload_len == 0)
        putchar('-');
    for (i = 0; i < f->payload_len; i++)
        printf("%02x", f->payload[i]);
    if (f->type == OPTITAC_T_CONTACT) {
        optitac_contact_t c;
        typed = optitac_decode_contact(f, &c) == 0 ? "1" : "0";
    } else if (f->type == OPTITAC_T_STATUS) {
        optitac_status_t s;
        typed = optitac_decode_status(f, &s) == 0 ? "1" : "0";
    } else if (f->type == OPTITAC_T_ACK) {
        optitac_ack_t a;
        typed = optitac_decode_ack(f, &a) == 0 ? "1" : "0";
    }
    printf(" %s\n", typed);
}

static void print_counters(long rec, const optitac_counters_t *c)
{
    if (rec >= 0)
        printf("C %ld ", rec);
    else
        printf("C ");
    printf("%lu %lu %lu %lu %lu %lu\n", (unsigned long)c->frames, (unsigned long)c->cobs,
           (unsigned long)c->length, (unsigned long)c->crc, (unsigned long)c->version,
           (unsigned long)c->overflow);
}

int main(int argc, char **argv)
{
    int records = 0, i;
    const char *path = NULL;
    FILE *fp = stdin;
    optitac_decoder_t d;
    optitac_frame_t f;
    int ch;
    for (i = 1; i < argc; i++) {
        if (strcmp(argv[i], "-r") == 0)
            records = 1;
        else
            path = argv[i];
    }
    if (path != NULL && strcmp(path, "-") != 0) {
        fp = fopen(path, "rb");
        if (fp == NULL) {
            perror(path);
            return 2;
        }
    }
    if (!records) {
        optitac_decoder_init(&d);
        while ((ch = getc(fp)) != EOF)
            if (optitac_decoder_feed(&d, (uint8_t)ch, &f) == OPTITAC_FEED_FRAME)
                print_frame(-1, &f);
        print_counters(-1, &d.counters);
    } else {
        long rec = 0;
        for (;;) {
            unsigned char hdr[4];
            unsigned long len, k;
            if (fread(hdr, 1, 4, fp) != 4)
                break;
            len = (unsigned long)hdr[0] | ((unsigned long)hdr[1] << 8) | ((unsigned long)hdr[2] << 16) |
                  ((unsigned long)hdr[3] << 24);
            optitac_decoder_init(&d);
            for (k = 0; k < len && (ch = getc(fp)) != EOF; k++)
                if (optitac_decoder_feed(&d, (uint8_t)ch, &f) == OPTITAC_FEED_FRAME)
                    print_frame(rec, &f);
            print_counters(rec, &d.counters);
            rec++;
        }
    }
    if (fp != stdin)
        fclose(fp);
    return 0;
}
