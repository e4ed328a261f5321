/*
 * serial_board.c - reference device side of the zplatform serial board
 * protocol, version 1 (docs/serial-protocol.md).
 *
 * Portable C99, no allocation, no libc beyond <string.h>. The board's port
 * provides six hooks (below) and calls:
 *
 *   sb_init(&dev)                    once at start-up;
 *   sb_rx_byte(&dev, byte, now_ms)   for every byte received on the serial port
 *                                    (from the UART ISR's ring buffer, say);
 *   sb_poll(&dev, now_ms)            often (main loop): applies the watchdog.
 *
 * Replies are sent from inside sb_rx_byte through sb_hw_send(), complete
 * frames only (COBS + 0x00 delimiter). Build the self-test on a host with
 *   gcc -std=c99 -Wall -DSB_SELFTEST serial_board.c -o sb_selftest && ./sb_selftest
 * which prints the frames of the worked example in the spec.
 */

#include <stddef.h>
#include <stdint.h>
#include <string.h>

#ifndef SB_DIGITAL_PINS
#define SB_DIGITAL_PINS 8 /* <= 64 */
#endif
#ifndef SB_ANALOG_PINS
#define SB_ANALOG_PINS 1 /* <= 16 */
#endif
#ifndef SB_WATCHDOG_MS
#define SB_WATCHDOG_MS 200 /* 0: no watchdog */
#endif

#define SB_VERSION 1u
#define SB_MSG_HELLO 0x01u
#define SB_MSG_WRITE 0x02u
#define SB_MSG_READ 0x03u
#define SB_MSG_ERROR 0x7Fu
#define SB_MSG_HELLO_ACK 0x81u
#define SB_MSG_INPUTS 0x82u

#define SB_ERR_BAD_CRC 1u
#define SB_ERR_BAD_VERSION 2u
#define SB_ERR_BAD_TYPE 3u
#define SB_ERR_BAD_LENGTH 4u
#define SB_ERR_NOT_READY 5u

#define SB_HEADER 4u
#define SB_IO_PAYLOAD (8u + 4u * SB_ANALOG_PINS)
#define SB_MAX_BODY (SB_HEADER + 8u + 4u * 16u + 2u) /* 78 */
#define SB_MAX_WIRE (SB_MAX_BODY + SB_MAX_BODY / 254u + 2u)

/* ---- hooks the board's port implements ---------------------------------- */

/* Drive the digital outputs: bit i = pin i (ignore bits of input pins). */
void sb_hw_write_digital(uint64_t outputs);
/* Drive analog output `pin` to `volts` (ignore analog inputs). */
void sb_hw_write_analog(uint8_t pin, float volts);
/* Sample every digital pin's level now, outputs included: bit i = pin i. */
uint64_t sb_hw_read_digital(void);
/* Sample analog pin `pin` now, in volts. */
float sb_hw_read_analog(uint8_t pin);
/* Drive every output to its safe value (must match the mission's). */
void sb_hw_safe(void);
/* Send `n` bytes on the serial port (a whole frame; may block briefly). */
void sb_hw_send(const uint8_t *data, size_t n);

/* ---- state ---------------------------------------------------------------- */

typedef struct sb_device {
    uint8_t rx[SB_MAX_WIRE]; /* COBS bytes of the frame being received */
    size_t rx_len;
    int overflow; /* dropping bytes up to the next 0x00 */
    int ready;    /* a HELLO was answered */
    int armed;    /* a WRITE arrived since the last safing */
    uint32_t last_write_ms;
} sb_device;

/* ---- CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection -------- */

uint16_t sb_crc16(const uint8_t *data, size_t n)
{
    uint16_t crc = 0xFFFFu;
    size_t i;
    int b;
    for (i = 0; i < n; i++) {
        crc ^= (uint16_t)((uint16_t)data[i] << 8);
        for (b = 0; b < 8; b++) {
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
        }
    }
    return crc;
}

/* ---- COBS ------------------------------------------------------------------ */

/* Encode src[0..n) into dst, then a 0x00; returns the bytes written.
 * dst must hold n + n / 254 + 2 bytes. */
size_t sb_cobs_encode(const uint8_t *src, size_t n, uint8_t *dst)
{
    size_t code_at = 0, out = 1, i;
    uint8_t code = 1;
    for (i = 0; i < n; i++) {
        if (src[i] == 0) {
            dst[code_at] = code;
            code_at = out++;
            code = 1;
        } else {
            dst[out++] = src[i];
            if (++code == 0xFFu) {
                dst[code_at] = code;
                code_at = out++;
                code = 1;
            }
        }
    }
    dst[code_at] = code;
    dst[out++] = 0;
    return out;
}

/* Decode one block (no delimiter) into dst (cap bytes); returns its length,
 * or -1 if malformed or too long. */
long sb_cobs_decode(const uint8_t *src, size_t n, uint8_t *dst, size_t cap)
{
    size_t i = 0, out = 0;
    while (i < n) {
        uint8_t code = src[i];
        size_t end, j;
        if (code == 0) return -1;
        end = i + code;
        if (end > n) return -1;
        for (j = i + 1; j < end; j++) {
            if (src[j] == 0 || out >= cap) return -1;
            dst[out++] = src[j];
        }
        i = end;
        if (code != 0xFFu && i < n) {
            if (out >= cap) return -1;
            dst[out++] = 0;
        }
    }
    return (long)out;
}

/* ---- little-endian fields (independent of the CPU's byte order) ----------- */

static void put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}

static uint16_t get_u16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }

static void put_u64(uint8_t *p, uint64_t v)
{
    int i;
    for (i = 0; i < 8; i++) p[i] = (uint8_t)(v >> (8 * i));
}

static uint64_t get_u64(const uint8_t *p)
{
    uint64_t v = 0;
    int i;
    for (i = 7; i >= 0; i--) v = (v << 8) | p[i];
    return v;
}

static void put_f32(uint8_t *p, float f)
{
    uint32_t u;
    memcpy(&u, &f, 4); /* IEEE-754 binary32 assumed (every MCU with an FPU or soft-float) */
    p[0] = (uint8_t)u;
    p[1] = (uint8_t)(u >> 8);
    p[2] = (uint8_t)(u >> 16);
    p[3] = (uint8_t)(u >> 24);
}

static float get_f32(const uint8_t *p)
{
    uint32_t u = (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) |
                 ((uint32_t)p[3] << 24);
    float f;
    memcpy(&f, &u, 4);
    return f;
}

/* ---- sending ---------------------------------------------------------------- */

static void send_frame(uint8_t type, uint16_t seq, const uint8_t *payload, size_t n)
{
    uint8_t body[SB_MAX_BODY];
    uint8_t wire[SB_MAX_WIRE];
    body[0] = SB_VERSION;
    body[1] = type;
    put_u16(body + 2, seq);
    if (n) memcpy(body + SB_HEADER, payload, n);
    put_u16(body + SB_HEADER + n, sb_crc16(body, SB_HEADER + n));
    sb_hw_send(wire, sb_cobs_encode(body, SB_HEADER + n + 2, wire));
}

static void send_error(uint8_t code, uint16_t seq, uint8_t bad_type)
{
    uint8_t p[2];
    p[0] = code;
    p[1] = bad_type;
    send_frame(SB_MSG_ERROR, seq, p, 2);
}

static void send_inputs(uint16_t seq)
{
    uint8_t p[SB_IO_PAYLOAD];
    uint8_t i;
    uint64_t levels = sb_hw_read_digital();
#if SB_DIGITAL_PINS < 64
    levels &= ((uint64_t)1 << SB_DIGITAL_PINS) - 1u;
#endif
    put_u64(p, levels);
    for (i = 0; i < SB_ANALOG_PINS; i++) put_f32(p + 8 + 4 * i, sb_hw_read_analog(i));
    send_frame(SB_MSG_INPUTS, seq, p, sizeof p);
}

/* ---- dispatch ----------------------------------------------------------------- */

static void handle_body(sb_device *dev, const uint8_t *body, size_t n, uint32_t now_ms)
{
    uint8_t type;
    uint16_t seq;
    size_t len;
    if (n < SB_HEADER + 2 || n > SB_MAX_BODY ||
        sb_crc16(body, n - 2) != get_u16(body + n - 2)) {
        send_error(SB_ERR_BAD_CRC, 0, 0); /* header not trustworthy */
        return;
    }
    type = body[1];
    seq = get_u16(body + 2);
    len = n - SB_HEADER - 2;
    if (body[0] != SB_VERSION) {
        send_error(SB_ERR_BAD_VERSION, seq, type);
        return;
    }
    switch (type) {
    case SB_MSG_HELLO: {
        uint8_t p[4];
        if (len != 0) {
            send_error(SB_ERR_BAD_LENGTH, seq, type);
            return;
        }
        dev->ready = 1;
        p[0] = SB_DIGITAL_PINS;
        p[1] = SB_ANALOG_PINS;
        put_u16(p + 2, SB_WATCHDOG_MS);
        send_frame(SB_MSG_HELLO_ACK, seq, p, 4);
        return;
    }
    case SB_MSG_WRITE: {
        uint8_t i;
        if (!dev->ready) {
            send_error(SB_ERR_NOT_READY, seq, type);
            return;
        }
        if (len != SB_IO_PAYLOAD) {
            send_error(SB_ERR_BAD_LENGTH, seq, type);
            return;
        }
        sb_hw_write_digital(get_u64(body + SB_HEADER));
        for (i = 0; i < SB_ANALOG_PINS; i++)
            sb_hw_write_analog(i, get_f32(body + SB_HEADER + 8 + 4 * i));
        dev->armed = 1;
        dev->last_write_ms = now_ms;
        send_inputs(seq);
        return;
    }
    case SB_MSG_READ:
        if (!dev->ready) {
            send_error(SB_ERR_NOT_READY, seq, type);
            return;
        }
        if (len != 0) {
            send_error(SB_ERR_BAD_LENGTH, seq, type);
            return;
        }
        send_inputs(seq);
        return;
    default:
        send_error(SB_ERR_BAD_TYPE, seq, type);
        return;
    }
}

void sb_init(sb_device *dev)
{
    memset(dev, 0, sizeof *dev);
    sb_hw_safe();
}

void sb_rx_byte(sb_device *dev, uint8_t byte, uint32_t now_ms)
{
    uint8_t body[SB_MAX_BODY];
    long n;
    if (byte != 0) {
        if (dev->overflow) return;
        if (dev->rx_len >= sizeof dev->rx) { /* no delimiter in time: resynchronise */
            dev->overflow = 1;
            dev->rx_len = 0;
            send_error(SB_ERR_BAD_CRC, 0, 0);
            return;
        }
        dev->rx[dev->rx_len++] = byte;
        return;
    }
    if (dev->overflow || dev->rx_len == 0) { /* end of a dropped frame, or an empty one */
        dev->overflow = 0;
        dev->rx_len = 0;
        return;
    }
    n = sb_cobs_decode(dev->rx, dev->rx_len, body, sizeof body);
    dev->rx_len = 0;
    if (n < 0) {
        send_error(SB_ERR_BAD_CRC, 0, 0);
        return;
    }
    handle_body(dev, body, (size_t)n, now_ms);
}

void sb_poll(sb_device *dev, uint32_t now_ms)
{
    /* unsigned subtraction: correct across the 49-day wrap of a ms counter */
    if (SB_WATCHDOG_MS && dev->armed && (uint32_t)(now_ms - dev->last_write_ms) > SB_WATCHDOG_MS) {
        sb_hw_safe();
        dev->armed = 0;
    }
}

#ifdef SB_SELFTEST
/* A host build: stub hardware (outputs read back; pin 4 wired high) and the
 * worked example of docs/serial-protocol.md, printed as hex, one frame a line. */
#include <stdio.h>

static uint64_t stub_dout;
static float stub_aout[SB_ANALOG_PINS ? SB_ANALOG_PINS : 1];

void sb_hw_write_digital(uint64_t outputs) { stub_dout = outputs; }
void sb_hw_write_analog(uint8_t pin, float volts) { stub_aout[pin] = volts; }
uint64_t sb_hw_read_digital(void) { return stub_dout | 0x10u; }
float sb_hw_read_analog(uint8_t pin) { return stub_aout[pin]; }
void sb_hw_safe(void) { stub_dout = 0; }
void sb_hw_send(const uint8_t *data, size_t n)
{
    size_t i;
    for (i = 0; i < n; i++) printf(i ? " %02x" : "%02x", data[i]);
    printf("\n");
}

static void feed(sb_device *dev, const char *hex, uint32_t now_ms)
{
    unsigned int b;
    while (sscanf(hex, "%2x", &b) == 1) {
        sb_rx_byte(dev, (uint8_t)b, now_ms);
        hex += 2;
        while (*hex == ' ') hex++;
    }
}

int main(void)
{
    sb_device dev;
    sb_init(&dev);
    printf("crc %04x\n", sb_crc16((const uint8_t *)"123456789", 9));
    feed(&dev, "03 01 01 01 03 44 c5 00", 0);                                          /* HELLO */
    feed(&dev, "de ad 00", 0);                                                         /* garbage */
    feed(&dev, "04 01 02 01 02 05 01 01 01 01 01 01 01 01 05 c0 3f df 2b 00", 10); /* WRITE */
    return 0;
}
#endif
