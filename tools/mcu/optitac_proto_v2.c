/* optitac_proto_v2.c - OptiTac serial protocol v2 messages (see optitac_proto_v2.h). */
#include "optitac_proto_v2.h"

static uint16_t get16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }

static void put16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)(v >> 8);
}

int optitac_decode_contact2(const optitac_frame_t *f, optitac_contact2_t *o)
{
    const uint8_t *p = f->payload;
    if (f->type != OPTITAC_T_CONTACT2 || f->payload_len != OPTITAC_CONTACT2_PAYLOAD)
        return -1;
    o->sensor_id = p[0];
    o->flags = p[1];
    o->frame = get16(p + 2);
    o->index = p[4];
    o->n_contacts = p[5];
    o->contact_id = p[6];
    o->shape = p[7];
    o->x = (int16_t)get16(p + 8);
    o->y = (int16_t)get16(p + 10);
    o->major = get16(p + 12);
    o->minor = get16(p + 14);
    o->angle = (int16_t)get16(p + 16);
    o->strength = get16(p + 18);
    o->depth = get16(p + 20);
    o->force = get16(p + 22);
    o->confidence = p[24];
    /* p[25] reserved */
    o->age_us = get16(p + 26);
    return 0;
}

int optitac_decode_release(const optitac_frame_t *f, optitac_release_t *o)
{
    const uint8_t *p = f->payload;
    if (f->type != OPTITAC_T_RELEASE || f->payload_len != OPTITAC_RELEASE_PAYLOAD)
        return -1;
    o->sensor_id = p[0];
    o->contact_id = p[1];
    o->frame = get16(p + 2);
    o->touch_frame = get16(p + 4);
    return 0;
}

int optitac_decode_motion(const optitac_frame_t *f, optitac_motion_t *o)
{
    const uint8_t *p = f->payload;
    if (f->type != OPTITAC_T_MOTION || f->payload_len != OPTITAC_MOTION_PAYLOAD)
        return -1;
    o->sensor_id = p[0];
    o->flags = p[1];
    o->frame = get16(p + 2);
    o->index = p[4];
    o->contact_id = p[5];
    o->vx = (int16_t)get16(p + 6);
    o->vy = (int16_t)get16(p + 8);
    o->slide_frame = get16(p + 10);
    o->vibration = get16(p + 12);
    return 0;
}

size_t optitac_encode_set_protocol(uint16_t seq, uint32_t t_us, uint8_t version, uint8_t *out, size_t out_cap)
{
    return optitac_encode_frame(OPTITAC_T_SET_PROTOCOL, seq, t_us, &version, 1u, out, out_cap);
}

size_t optitac_encode_contact2(uint16_t seq, uint32_t t_us, const optitac_contact2_t *c, uint8_t *out,
                               size_t out_cap)
{
    uint8_t p[OPTITAC_CONTACT2_PAYLOAD];
    p[0] = c->sensor_id;
    p[1] = (uint8_t)(c->flags & 0x7Fu);
    put16(p + 2, c->frame);
    p[4] = c->index;
    p[5] = c->n_contacts;
    p[6] = c->contact_id;
    p[7] = c->shape;
    put16(p + 8, (uint16_t)c->x);
    put16(p + 10, (uint16_t)c->y);
    put16(p + 12, c->major);
    put16(p + 14, c->minor);
    put16(p + 16, (uint16_t)c->angle);
    put16(p + 18, c->strength);
    put16(p + 20, c->depth);
    put16(p + 22, c->force);
    p[24] = c->confidence;
    p[25] = 0u;
    put16(p + 26, c->age_us);
    return optitac_encode_frame(OPTITAC_T_CONTACT2, seq, t_us, p, sizeof p, out, out_cap);
}

size_t optitac_encode_release(uint16_t seq, uint32_t t_us, const optitac_release_t *r, uint8_t *out,
                              size_t out_cap)
{
    uint8_t p[OPTITAC_RELEASE_PAYLOAD];
    p[0] = r->sensor_id;
    p[1] = r->contact_id;
    put16(p + 2, r->frame);
    put16(p + 4, r->touch_frame);
    return optitac_encode_frame(OPTITAC_T_RELEASE, seq, t_us, p, sizeof p, out, out_cap);
}

size_t optitac_encode_motion(uint16_t seq, uint32_t t_us, const optitac_motion_t *m, uint8_t *out,
                             size_t out_cap)
{
    uint8_t p[OPTITAC_MOTION_PAYLOAD];
    p[0] = m->sensor_id;
    p[1] = (uint8_t)(m->flags & 0x3Fu);
    put16(p + 2, m->frame);
    p[4] = m->index;
    p[5] = m->contact_id;
    put16(p + 6, (uint16_t)m->vx);
    put16(p + 8, (uint16_t)m->vy);
    put16(p + 10, m->slide_frame);
    put16(p + 12, m->vibration);
    return optitac_encode_frame(OPTITAC_T_MOTION, seq, t_us, p, sizeof p, out, out_cap);
}
