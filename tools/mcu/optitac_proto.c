/* optitac_proto.c - OptiTac serial protocol v1, MCU side. See optitac_proto.h. */
#include "optitac_proto.h"

#include <string.h>

static uint16_t rd16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }

static uint32_t rd32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static void wr16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)(v >> 8);
}

static void wr32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)((v >> 8) & 0xFFu);
    p[2] = (uint8_t)((v >> 16) & 0xFFu);
    p[3] = (uint8_t)(v >> 24);
}

uint16_t optitac_crc16_update(uint16_t crc, const uint8_t *data, size_t len)
{
    size_t i;
    int bit;
    for (i = 0; i < len; i++) {
        crc ^= (uint16_t)((uint16_t)data[i] << 8);
        for (bit = 0; bit < 8; bit++)
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
    }
    return crc;
}

uint16_t optitac_crc16(const uint8_t *data, size_t len) { return optitac_crc16_update(0xFFFFu, data, len); }

/* ---------------------------------------------------------------- decoder */

void optitac_decoder_reset(optitac_decoder_t *d)
{
    d->len = 0;
    d->encoded = 0;
    d->code = 0;
    d->remaining = 0;
    d->skipping = 0;
}

void optitac_decoder_init(optitac_decoder_t *d)
{
    memset(d, 0, sizeof *d);
    optitac_decoder_reset(d);
}

static optitac_feed_result_t complete(optitac_decoder_t *d, optitac_frame_t *frame)
{
    const uint8_t n = d->len;
    const uint8_t *b = d->buf;
    if (d->remaining != 0) { /* a COBS code pointed past the delimiter */
        d->counters.cobs++;
        return OPTITAC_FEED_ERR_COBS;
    }
    if (n < OPTITAC_MIN_FRAME) {
        d->counters.length++;
        return OPTITAC_FEED_ERR_LENGTH;
    }
    if (optitac_crc16(b, (size_t)(n - OPTITAC_CRC_SIZE)) != rd16(b + n - OPTITAC_CRC_SIZE)) {
        d->counters.crc++;
        return OPTITAC_FEED_ERR_CRC;
    }
    if (b[0] != OPTITAC_VERSION) {
        d->counters.version++;
        return OPTITAC_FEED_ERR_VERSION;
    }
    d->counters.frames++;
    if (frame != NULL) {
        frame->type = b[1];
        frame->seq = rd16(b + 2);
        frame->t_us = rd32(b + 4);
        frame->payload = b + OPTITAC_HEADER_SIZE;
        frame->payload_len = (uint8_t)(n - OPTITAC_MIN_FRAME);
    }
    return OPTITAC_FEED_FRAME;
}

optitac_feed_result_t optitac_decoder_feed(optitac_decoder_t *d, uint8_t byte, optitac_frame_t *frame)
{
    if (byte == 0u) { /* delimiter */
        optitac_feed_result_t r = OPTITAC_FEED_NONE;
        if (!d->skipping && d->encoded != 0u)
            r = complete(d, frame); /* buf stays intact until the next byte: frame->payload valid */
        optitac_decoder_reset(d);
        return r;
    }
    if (d->skipping)
        return OPTITAC_FEED_NONE;
    if (d->encoded >= OPTITAC_MAX_ENCODED) {
        d->skipping = 1;
        d->counters.overflow++;
        return OPTITAC_FEED_ERR_OVERFLOW;
    }
    d->encoded++;
    if (d->remaining == 0u) { /* a COBS code byte: the previous block (if < 0xFF) ended in a zero */
        if (d->code != 0u && d->code != 0xFFu)
            d->buf[d->len++] = 0u;
        d->code = byte;
        d->remaining = (uint8_t)(byte - 1u);
    } else {
        d->buf[d->len++] = byte;
        d->remaining--;
    }
    return OPTITAC_FEED_NONE;
}

/* ---------------------------------------------------------------- messages */

int optitac_decode_contact(const optitac_frame_t *f, optitac_contact_t *o)
{
    const uint8_t *p = f->payload;
    if (f->type != OPTITAC_T_CONTACT || f->payload_len != OPTITAC_CONTACT_PAYLOAD)
        return -1;
    o->sensor_id = p[0];
    o->flags = p[1];
    o->x = (int16_t)rd16(p + 2);
    o->y = (int16_t)rd16(p + 4);
    o->major = rd16(p + 6);
    o->minor = rd16(p + 8);
    o->angle = (int16_t)rd16(p + 10);
    o->strength = rd16(p + 12);
    o->shape = p[14];
    o->confidence = p[15];
    o->age_us = rd16(p + 16);
    return 0;
}

int optitac_decode_status(const optitac_frame_t *f, optitac_status_t *o)
{
    const uint8_t *p = f->payload;
    if (f->type != OPTITAC_T_STATUS || f->payload_len != OPTITAC_STATUS_PAYLOAD)
        return -1;
    o->sensor_id = p[0];
    o->state = p[1];
    o->fps_x10 = rd16(p + 2);
    o->frames_dropped = rd32(p + 4);
    o->camera_errors = rd32(p + 8);
    o->link_errors = rd32(p + 12);
    o->cpu_temp_c_x10 = (int16_t)rd16(p + 16);
    o->calibration_id = rd32(p + 18);
    return 0;
}

int optitac_decode_ack(const optitac_frame_t *f, optitac_ack_t *o)
{
    if (f->type != OPTITAC_T_ACK || f->payload_len != OPTITAC_ACK_PAYLOAD)
        return -1;
    o->seq_acked = rd16(f->payload);
    o->result = f->payload[2];
    return 0;
}

size_t optitac_encode_frame(uint8_t type, uint16_t seq, uint32_t t_us, const uint8_t *payload,
                            size_t payload_len, uint8_t *out, size_t out_cap)
{
    uint8_t raw[OPTITAC_MAX_DECODED];
    size_t n, i, o, code_idx;
    uint8_t code;
    if (payload_len > OPTITAC_MAX_PAYLOAD || (payload_len > 0u && payload == NULL))
        return 0;
    n = OPTITAC_HEADER_SIZE + payload_len + OPTITAC_CRC_SIZE;
    if (out == NULL || out_cap < n + 2u) /* COBS adds one byte (n < 254), plus the delimiter */
        return 0;
    raw[0] = (uint8_t)OPTITAC_VERSION;
    raw[1] = type;
    wr16(raw + 2, seq);
    wr32(raw + 4, t_us);
    if (payload_len > 0u)
        memcpy(raw + OPTITAC_HEADER_SIZE, payload, payload_len);
    wr16(raw + OPTITAC_HEADER_SIZE + payload_len, optitac_crc16(raw, OPTITAC_HEADER_SIZE + payload_len));
    /* COBS */
    code_idx = 0;
    o = 1;
    code = 1;
    for (i = 0; i < n; i++) {
        if (raw[i] == 0u) {
            out[code_idx] = code;
            code_idx = o++;
            code = 1;
        } else {
            out[o++] = raw[i];
            code++;
            if (code == 0xFFu && i + 1u < n) {
                out[code_idx] = code;
                code_idx = o++;
                code = 1;
            }
        }
    }
    out[code_idx] = code;
    out[o++] = 0u;
    return o;
}

size_t optitac_encode_ping(uint16_t seq, uint32_t t_us, uint8_t *out, size_t out_cap)
{
    return optitac_encode_frame(OPTITAC_T_PING, seq, t_us, NULL, 0, out, out_cap);
}

size_t optitac_encode_tare(uint16_t seq, uint32_t t_us, uint8_t *out, size_t out_cap)
{
    return optitac_encode_frame(OPTITAC_T_TARE, seq, t_us, NULL, 0, out, out_cap);
}

size_t optitac_encode_stream(uint16_t seq, uint32_t t_us, uint8_t on, uint8_t rate_divider,
                             uint8_t *out, size_t out_cap)
{
    uint8_t p[2];
    p[0] = on;
    p[1] = rate_divider;
    return optitac_encode_frame(OPTITAC_T_STREAM, seq, t_us, p, sizeof p, out, out_cap);
}

size_t optitac_encode_set_threshold(uint16_t seq, uint32_t t_us, uint16_t threshold,
                                    uint8_t *out, size_t out_cap)
{
    uint8_t p[2];
    wr16(p, threshold);
    return optitac_encode_frame(OPTITAC_T_SET_THRESHOLD, seq, t_us, p, sizeof p, out, out_cap);
}
