/*
 * optitac_proto.h - OptiTac serial protocol v1, MCU side (reference implementation).
 *
 * C99, no malloc, no I/O. The interface control document is docs/protocol.md.
 *
 * Wire frame: COBS(header | payload | crc) 0x00, little-endian fields:
 *   header: u8 version (=1), u8 type, u16 seq, u32 t_us          (8 bytes)
 *   crc:    u16 CRC-16/CCITT-FALSE over header and payload       (2 bytes)
 *
 * Receiving: optitac_decoder_init() once, then optitac_decoder_feed() for every byte
 * received (e.g. from the UART RX interrupt or DMA ring); it returns OPTITAC_FEED_FRAME
 * when a validated frame is available in *frame (valid until the next feed call), then
 * decode it with optitac_decode_contact/status/ack().
 * Sending: optitac_encode_ping/tare/stream/set_threshold() write a complete wire frame
 * (delimiter included) into a caller buffer of at least OPTITAC_MAX_WIRE bytes.
 */
#ifndef OPTITAC_PROTO_H
#define OPTITAC_PROTO_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define OPTITAC_VERSION 1u
#define OPTITAC_HEADER_SIZE 8u
#define OPTITAC_CRC_SIZE 2u
#define OPTITAC_MIN_FRAME (OPTITAC_HEADER_SIZE + OPTITAC_CRC_SIZE)
/* Longest COBS-encoded frame accepted, delimiter excluded. */
#define OPTITAC_MAX_ENCODED 64u
#define OPTITAC_MAX_DECODED (OPTITAC_MAX_ENCODED - 1u)
#define OPTITAC_MAX_PAYLOAD (OPTITAC_MAX_DECODED - OPTITAC_MIN_FRAME)
/* Room for one encoded frame plus its delimiter. */
#define OPTITAC_MAX_WIRE (OPTITAC_MAX_ENCODED + 1u)

/* Message types */
#define OPTITAC_T_CONTACT 0x01u
#define OPTITAC_T_STATUS 0x02u
#define OPTITAC_T_PING 0x10u
#define OPTITAC_T_TARE 0x11u
#define OPTITAC_T_STREAM 0x12u
#define OPTITAC_T_SET_THRESHOLD 0x13u
#define OPTITAC_T_ACK 0x7Fu

#define OPTITAC_CONTACT_PAYLOAD 18u
#define OPTITAC_STATUS_PAYLOAD 22u
#define OPTITAC_ACK_PAYLOAD 3u

/* CONTACT flags */
#define OPTITAC_F_CONTACT 0x01u
#define OPTITAC_F_CALIBRATED 0x02u
#define OPTITAC_F_SATURATED 0x04u
#define OPTITAC_F_DEGRADED 0x08u
#define OPTITAC_F_MORE_CONTACTS 0x10u

/* STATUS state bits */
#define OPTITAC_S_STREAMING 0x01u
#define OPTITAC_S_BASELINE_READY 0x02u
#define OPTITAC_S_DEGRADED 0x04u
#define OPTITAC_S_CAMERA_FAULT 0x08u
#define OPTITAC_S_LIGHT_CHANGE 0x10u        /* common-mode light change since the last STATUS (not a contact) */
#define OPTITAC_S_CALIBRATION_UNSAVED 0x20u /* running on a bundle that could not be saved */

/* ACK result codes */
#define OPTITAC_R_OK 0u
#define OPTITAC_R_UNKNOWN_COMMAND 1u
#define OPTITAC_R_BAD_LENGTH 2u
#define OPTITAC_R_OUT_OF_RANGE 3u
#define OPTITAC_R_BUSY 4u

/* SET_THRESHOLD range, 0.0001 relative units per LSB */
#define OPTITAC_THRESHOLD_MIN 10u
#define OPTITAC_THRESHOLD_MAX 5000u

/* Return values of optitac_decoder_feed() */
typedef enum {
    OPTITAC_FEED_NONE = 0,     /* byte consumed, nothing completed */
    OPTITAC_FEED_FRAME = 1,    /* *frame holds a validated frame */
    OPTITAC_FEED_ERR_COBS = -1,
    OPTITAC_FEED_ERR_LENGTH = -2,
    OPTITAC_FEED_ERR_CRC = -3,
    OPTITAC_FEED_ERR_VERSION = -4,
    OPTITAC_FEED_ERR_OVERFLOW = -5 /* reported once, on the byte that overflowed */
} optitac_feed_result_t;

typedef struct {
    uint32_t frames;   /* accepted */
    uint32_t cobs;     /* COBS code pointing past the end of the frame */
    uint32_t length;   /* decoded frame shorter than 10 bytes */
    uint32_t crc;
    uint32_t version;
    uint32_t overflow; /* more than OPTITAC_MAX_ENCODED bytes before a delimiter */
} optitac_counters_t;

typedef struct {
    uint8_t type;
    uint16_t seq;
    uint32_t t_us;
    const uint8_t *payload; /* points into the decoder; valid until the next feed */
    uint8_t payload_len;
} optitac_frame_t;

typedef struct {
    uint8_t buf[OPTITAC_MAX_DECODED + 1u]; /* decoded bytes of the current frame */
    uint8_t len;       /* decoded bytes so far */
    uint8_t encoded;   /* encoded bytes so far (bounded by OPTITAC_MAX_ENCODED) */
    uint8_t code;      /* current COBS code byte */
    uint8_t remaining; /* data bytes left in the current COBS block */
    uint8_t skipping;  /* overflowed: drop bytes until the next delimiter */
    optitac_counters_t counters;
} optitac_decoder_t;

typedef struct {
    uint8_t sensor_id;
    uint8_t flags;
    int16_t x;          /* 0.01 mm */
    int16_t y;          /* 0.01 mm */
    uint16_t major;     /* 0.01 mm */
    uint16_t minor;     /* 0.01 mm */
    int16_t angle;      /* 0.01 deg, -9000..9000 */
    uint16_t strength;  /* 0.01 relative units * mm^2 */
    uint8_t shape;      /* 0 none, 1 edge, 2 circle, 3 square, 4 ellipse, 5 triangle, 255 unknown */
    uint8_t confidence; /* 0..255 */
    uint16_t age_us;    /* exposure to send, saturating */
} optitac_contact_t;

typedef struct {
    uint8_t sensor_id;
    uint8_t state;            /* OPTITAC_S_* bits */
    uint16_t fps_x10;
    uint32_t frames_dropped;
    uint32_t camera_errors;
    uint32_t link_errors;
    int16_t cpu_temp_c_x10;   /* -32768 unknown */
    uint32_t calibration_id;
} optitac_status_t;

typedef struct {
    uint16_t seq_acked;
    uint8_t result;
} optitac_ack_t;

/* CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor. */
uint16_t optitac_crc16_update(uint16_t crc, const uint8_t *data, size_t len);
uint16_t optitac_crc16(const uint8_t *data, size_t len);

void optitac_decoder_init(optitac_decoder_t *d);
/* Drop a partial frame, keep the counters. */
void optitac_decoder_reset(optitac_decoder_t *d);
optitac_feed_result_t optitac_decoder_feed(optitac_decoder_t *d, uint8_t byte, optitac_frame_t *frame);

/* 0 on success, -1 when the frame has another type or payload length. */
int optitac_decode_contact(const optitac_frame_t *f, optitac_contact_t *out);
int optitac_decode_status(const optitac_frame_t *f, optitac_status_t *out);
int optitac_decode_ack(const optitac_frame_t *f, optitac_ack_t *out);

/* Encode one frame (COBS + delimiter) into out; returns the bytes written, 0 if
 * out_cap is too small or payload_len > OPTITAC_MAX_PAYLOAD. */
size_t optitac_encode_frame(uint8_t type, uint16_t seq, uint32_t t_us, const uint8_t *payload,
                            size_t payload_len, uint8_t *out, size_t out_cap);
size_t optitac_encode_ping(uint16_t seq, uint32_t t_us, uint8_t *out, size_t out_cap);
size_t optitac_encode_tare(uint16_t seq, uint32_t t_us, uint8_t *out, size_t out_cap);
size_t optitac_encode_stream(uint16_t seq, uint32_t t_us, uint8_t on, uint8_t rate_divider,
                             uint8_t *out, size_t out_cap);
size_t optitac_encode_set_threshold(uint16_t seq, uint32_t t_us, uint16_t threshold,
                                    uint8_t *out, size_t out_cap);

#ifdef __cplusplus
}
#endif

#endif /* OPTITAC_PROTO_H */
