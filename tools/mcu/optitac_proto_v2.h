/*
 * optitac_proto_v2.h - OptiTac serial protocol v2 messages, MCU side (reference implementation).
 *
 * C99, no malloc, no I/O; docs/protocol.md section 8. Builds on optitac_proto.h (the framing,
 * the decoder and the v1 messages, unchanged): an MCU that never sends SET_PROTOCOL never sees
 * these messages and needs only optitac_proto.c.
 *
 * After optitac_encode_set_protocol(..., 2, ...) is acknowledged, the sensor sends per camera
 * frame one RELEASE for every contact the MCU was told of that is gone, then one CONTACT2 for
 * every contact (index 0 = the strongest; one with n_contacts 0 when there is none).
 * optitac_encode_contact2/release() are the sensor's encoders, kept here so the golden vectors
 * are checked against an encoder that is not the Python code under test.
 *
 * Protocol v3 (docs/protocol.md section 13): after optitac_encode_set_protocol(..., 3, ...) each CONTACT2
 * is followed by the MOTION (0x05) of the same contact (same frame and index): its velocity, whether it
 * slides, and the frame's vibration. An MCU on v1 or v2 never asks for it and never sees it.
 */
#ifndef OPTITAC_PROTO_V2_H
#define OPTITAC_PROTO_V2_H

#include "optitac_proto.h"

#ifdef __cplusplus
extern "C" {
#endif

#define OPTITAC_T_CONTACT2 0x03u
#define OPTITAC_T_RELEASE 0x04u
#define OPTITAC_T_MOTION 0x05u
#define OPTITAC_T_SET_PROTOCOL 0x14u

#define OPTITAC_CONTACT2_PAYLOAD 28u
#define OPTITAC_RELEASE_PAYLOAD 6u
#define OPTITAC_MOTION_PAYLOAD 14u

/* CONTACT2 flags */
#define OPTITAC_F2_CONTACT 0x01u
#define OPTITAC_F2_CALIBRATED 0x02u
#define OPTITAC_F2_SATURATED 0x04u
#define OPTITAC_F2_DEGRADED 0x08u
#define OPTITAC_F2_TOUCH 0x10u /* new to the MCU in this frame */
#define OPTITAC_F2_DEPTH 0x20u /* depth is calibrated */
#define OPTITAC_F2_FORCE 0x40u /* force is calibrated */

/* MOTION flags (protocol v3) */
#define OPTITAC_FM_VELOCITY 0x01u        /* vx, vy hold the contact's velocity */
#define OPTITAC_FM_SLIDING 0x02u         /* the contact slides */
#define OPTITAC_FM_SLIDE_BEGAN 0x04u     /* its slide was found in this frame */
#define OPTITAC_FM_VIBRATION 0x08u       /* vibration holds the frame's figure */
#define OPTITAC_FM_VIBRATING 0x10u       /* the frame vibrates above its quiet level */
#define OPTITAC_FM_VIBRATION_BEGAN 0x20u /* ... since this frame */

/* STATUS state bit 6: the sensor speaks v2 (or v3); bit 7: it speaks v3 */
#define OPTITAC_S_PROTOCOL_V2 0x40u
#define OPTITAC_S_PROTOCOL_V3 0x80u

typedef struct {
    uint8_t sensor_id;
    uint8_t flags;      /* OPTITAC_F2_* */
    uint16_t frame;     /* sensor frame counter: the same in every message of one camera frame */
    uint8_t index;      /* 0 .. n_contacts-1, strongest first */
    uint8_t n_contacts; /* 0 .. 4 */
    uint8_t contact_id; /* 1 .. 255, stable while the contact lasts; 0 none */
    uint8_t shape;      /* as CONTACT */
    int16_t x;          /* 0.01 mm */
    int16_t y;          /* 0.01 mm */
    uint16_t major;     /* 0.01 mm */
    uint16_t minor;     /* 0.01 mm */
    int16_t angle;      /* 0.01 deg, -9000..9000 */
    uint16_t strength;  /* 0.01 relative units * mm^2 */
    uint16_t depth;     /* 0.001 mm (0 unless OPTITAC_F2_DEPTH) */
    uint16_t force;     /* 0.001 N (0 unless OPTITAC_F2_FORCE) */
    uint8_t confidence; /* 0..255 */
    uint16_t age_us;    /* exposure to send, saturating */
} optitac_contact2_t;

typedef struct {
    uint8_t sensor_id;
    uint8_t contact_id;
    uint16_t frame;       /* the frame of the release (the first without the contact) */
    uint16_t touch_frame; /* the frame it touched in */
} optitac_release_t;

typedef struct {
    uint8_t sensor_id;
    uint8_t flags;        /* OPTITAC_FM_* */
    uint16_t frame;       /* as the CONTACT2 it follows */
    uint8_t index;        /* as the CONTACT2 it follows */
    uint8_t contact_id;   /* 0 without contact */
    int16_t vx;           /* 0.01 mm/s, sensor frame (0 unless OPTITAC_FM_VELOCITY) */
    int16_t vy;           /* 0.01 mm/s */
    uint16_t slide_frame; /* the frame the slide was found in (0 unless OPTITAC_FM_SLIDING) */
    uint16_t vibration;   /* 0.01 units of the sensor's noise (0 unless OPTITAC_FM_VIBRATION) */
} optitac_motion_t;

/* 0 on success, -1 when the frame has another type or payload length. */
int optitac_decode_contact2(const optitac_frame_t *f, optitac_contact2_t *out);
int optitac_decode_release(const optitac_frame_t *f, optitac_release_t *out);
int optitac_decode_motion(const optitac_frame_t *f, optitac_motion_t *out);

/* The MCU asks for protocol version 1, 2 or 3 (the sensor answers other values OUT_OF_RANGE; one that does
 * not know v3 answers 3 OUT_OF_RANGE too, and the MCU stays on v2). */
size_t optitac_encode_set_protocol(uint16_t seq, uint32_t t_us, uint8_t version, uint8_t *out, size_t out_cap);

/* The sensor's side (vectors, simulators): complete wire frames, 0 if out_cap is too small. */
size_t optitac_encode_contact2(uint16_t seq, uint32_t t_us, const optitac_contact2_t *c, uint8_t *out,
                               size_t out_cap);
size_t optitac_encode_release(uint16_t seq, uint32_t t_us, const optitac_release_t *r, uint8_t *out,
                              size_t out_cap);
size_t optitac_encode_motion(uint16_t seq, uint32_t t_us, const optitac_motion_t *m, uint8_t *out,
                             size_t out_cap);

#ifdef __cplusplus
}
#endif

#endif /* OPTITAC_PROTO_V2_H */
