/*
 * scanrig reference firmware for an ATmega328P board (Arduino Uno class) at 16 MHz.
 * Implements the scanrig line protocol v1 (../PROTOCOL.md).
 *
 * Wiring (Arduino pin names in brackets):
 *   PD2 [D2]  STEP of a step/dir driver        PD4 [D4]  DIR
 *   PD7 [D7]  driver ENABLE (active low)
 *   PD6 [D6]  light 0 PWM (OC0A)               PD5 [D5]  light 1 PWM (OC0B)
 *   PB3 [D11] light 2 PWM (OC2A)               PD3 [D3]  light 3 PWM (OC2B)
 *   PB0 [D8]  laser 0 MOSFET                   PB1 [D9]  laser 1 MOSFET
 *   PB4 [D12] camera trigger output (active high)
 * Lights and lasers drive logic-level MOSFETs; every output is low (off) after reset.
 *
 * Timers: Timer0 and Timer2 make the PWM (about 976 Hz); Timer0's overflow also counts time
 * (1.024 ms per tick). Timer1 makes the step pulses at STEP_RATE steps per second.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#ifndef F_CPU
#define F_CPU 16000000UL
#endif
#ifndef STEPS_PER_TURN
#define STEPS_PER_TURN 3200L /* the one place steps per turn is defined; reported by CAPS */
#endif
#ifndef STEP_RATE
#define STEP_RATE 3200L /* steps per second */
#endif
#define LIGHTS 4
#define LASERS 2
#define MAX_LINE 96
#define FW_NAME "scanrig-uno"
#define FW_VERSION "1.0.0"

/* ---- time ---------------------------------------------------------------------------- */
static volatile uint32_t ticks; /* Timer0 overflows, 1.024 ms each */
ISR(TIMER0_OVF_vect) { ticks++; }
static uint32_t now_ms(void) {
    uint32_t t;
    uint8_t s = SREG;
    cli();
    t = ticks;
    SREG = s;
    return t + (t >> 6) - (t >> 11); /* ~ x 1.024 */
}

/* ---- stepper --------------------------------------------------------------------------- */
static volatile int32_t pos, target;
static volatile uint8_t moving;
static volatile uint8_t done_pending;
ISR(TIMER1_COMPA_vect) {
    if (!moving) return;
    if (pos == target) {
        moving = 0;
        done_pending = 1;
        return;
    }
    if (target > pos) { PORTD |= _BV(PD4); pos++; } else { PORTD &= ~_BV(PD4); pos--; }
    PORTD |= _BV(PD2);
    __asm__ __volatile__("nop\n nop\n nop\n nop\n nop\n nop\n nop\n nop\n nop\n nop\n nop\n nop\n nop\n nop\n nop\n nop");
    PORTD &= ~_BV(PD2);
}
static int32_t read_pos(void) {
    int32_t p;
    uint8_t s = SREG;
    cli();
    p = pos;
    SREG = s;
    return p;
}

/* ---- UART ------------------------------------------------------------------------------ */
#define RX_SIZE 128
static volatile uint8_t rx_buf[RX_SIZE];
static volatile uint8_t rx_head, rx_tail;
static volatile uint8_t rt_status, rt_stop, rt_reset;
static volatile uint32_t last_rx_ms;
ISR(USART_RX_vect) {
    uint8_t b = UDR0;
    last_rx_ms = ticks;
    if (b == '?') { rt_status = 1; return; }
    if (b == '!') { rt_stop = 1; moving = 0; return; } /* stop at once, in the interrupt */
    if (b == 0x18) { rt_reset = 1; moving = 0; return; }
    uint8_t next = (uint8_t)((rx_head + 1) % RX_SIZE);
    if (next != rx_tail) { rx_buf[rx_head] = b; rx_head = next; }
}
static int rx_get(void) {
    if (rx_head == rx_tail) return -1;
    uint8_t b = rx_buf[rx_tail];
    rx_tail = (uint8_t)((rx_tail + 1) % RX_SIZE);
    return b;
}
static void tx(uint8_t b) {
    while (!(UCSR0A & _BV(UDRE0))) {}
    UDR0 = b;
}

/* ---- output lines ---------------------------------------------------------------------- */
static uint8_t checksum_mode;
static char out[MAX_LINE + 8];
static uint8_t out_len;
static void o_str(const char *s) { while (*s && out_len < MAX_LINE) out[out_len++] = *s++; }
static void o_long(int32_t v) { char b[12]; ltoa(v, b, 10); o_str(b); }
static void o_ulong(uint32_t v) { char b[12]; ultoa(v, b, 10); o_str(b); }
static void o_send(void) {
    uint8_t sum = 0, i;
    for (i = 0; i < out_len; i++) { sum ^= (uint8_t)out[i]; tx((uint8_t)out[i]); }
    if (checksum_mode) {
        static const char hex[] = "0123456789ABCDEF";
        tx('*'); tx((uint8_t)hex[sum >> 4]); tx((uint8_t)hex[sum & 15]);
    }
    tx('\n');
    out_len = 0;
}

/* ---- outputs --------------------------------------------------------------------------- */
static uint32_t laser_on_ms[LASERS];
static uint8_t laser_on[LASERS];
static uint8_t motor_on;
static uint32_t idle_since_ms;
static uint16_t limit_laser_s = 255;
static uint32_t limit_idle_ms = 10000, limit_watchdog_ms;
static uint8_t watchdog_tripped;

static void set_light(uint8_t i, uint8_t level) {
    switch (i) {
    case 0: OCR0A = level; if (level) TCCR0A |= _BV(COM0A1); else { TCCR0A &= ~_BV(COM0A1); PORTD &= ~_BV(PD6); } break;
    case 1: OCR0B = level; if (level) TCCR0A |= _BV(COM0B1); else { TCCR0A &= ~_BV(COM0B1); PORTD &= ~_BV(PD5); } break;
    case 2: OCR2A = level; if (level) TCCR2A |= _BV(COM2A1); else { TCCR2A &= ~_BV(COM2A1); PORTB &= ~_BV(PB3); } break;
    case 3: OCR2B = level; if (level) TCCR2A |= _BV(COM2B1); else { TCCR2A &= ~_BV(COM2B1); PORTD &= ~_BV(PD3); } break;
    }
}
static void set_laser(uint8_t i, uint8_t on) {
    uint8_t bit = i == 0 ? _BV(PB0) : _BV(PB1);
    if (on) PORTB |= bit; else PORTB &= (uint8_t)~bit;
    laser_on[i] = on;
    laser_on_ms[i] = now_ms();
}
static void set_motor(uint8_t on) {
    if (on) PORTD &= ~_BV(PD7); else PORTD |= _BV(PD7);
    motor_on = on;
    idle_since_ms = now_ms();
}

/* ---- motion ---------------------------------------------------------------------------- */
static uint16_t motion_id, last_move;
static void start_motion(int32_t to) {
    set_motor(1);
    last_move = last_move == 0xFFFF ? 1 : (uint16_t)(last_move + 1);
    motion_id = last_move;
    uint8_t s = SREG;
    cli();
    target = to;
    done_pending = 0;
    moving = 1;
    SREG = s;
}
static void report_end(const char *what) {
    o_str(what); o_str(" move="); o_ulong(motion_id); o_str(" pos="); o_long(read_pos()); o_send();
    motion_id = 0;
    idle_since_ms = now_ms();
}
static void stop_motion(void) {
    uint8_t was;
    uint8_t s = SREG;
    cli();
    was = moving || motion_id;
    moving = 0;
    target = pos;
    done_pending = 0;
    SREG = s;
    if (was && motion_id) report_end("@stopped");
}
static void everything_off(void) {
    uint8_t i;
    stop_motion();
    for (i = 0; i < LIGHTS; i++) set_light(i, 0);
    for (i = 0; i < LASERS; i++) set_laser(i, 0);
    set_motor(0);
}

/* ---- parsing --------------------------------------------------------------------------- */
static char line[MAX_LINE + 1];
static uint8_t line_len, line_overflow;
static uint8_t have_last_n;
static uint16_t last_n;
static char last_reply[MAX_LINE + 1];
static uint8_t last_reply_len;

static int hexval(char c) {
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    return -1;
}
/* Unsigned decimal word up to max; returns 0 on success. */
static int parse_u32(const char *s, uint32_t max, uint32_t *v) {
    uint32_t x = 0;
    uint8_t n = 0;
    if (!*s) return -1;
    for (; *s; s++, n++) {
        if (*s < '0' || *s > '9' || n >= 10) return -1;
        uint32_t d = (uint32_t)(*s - '0');
        if (x > (max - d) / 10) return -1;
        x = x * 10 + d;
    }
    *v = x;
    return 0;
}
/* Degrees with at most three decimals to thousandths. */
static int parse_millideg(const char *s, int32_t *v) {
    uint8_t neg = 0, frac_digits = 0, seen_point = 0, int_digits = 0;
    uint32_t x = 0;
    if (*s == '-') { neg = 1; s++; } else if (*s == '+') s++;
    for (; *s; s++) {
        if (*s == '.') { if (seen_point || !int_digits) return -1; seen_point = 1; continue; }
        if (*s < '0' || *s > '9') return -1;
        if (seen_point) { if (++frac_digits > 3) return -1; } else if (++int_digits > 7) return -1;
        x = x * 10 + (uint32_t)(*s - '0');
    }
    if (!int_digits || (seen_point && !frac_digits)) return -1;
    while (frac_digits++ < 3) x *= 10;
    if (x > 1000000000UL) return -1;
    *v = neg ? -(int32_t)x : (int32_t)x;
    return 0;
}
static int32_t millideg_to_steps(int32_t md) {
    int64_t num = (int64_t)md * STEPS_PER_TURN;
    return (int32_t)(num >= 0 ? (num + 180000) / 360000 : -((-num + 180000) / 360000));
}

static void reply_begin(uint8_t ok, uint8_t code, uint8_t numbered, uint16_t n) {
    out_len = 0;
    if (ok) o_str("ok"); else { o_str("error:"); o_ulong(code); }
    if (numbered) { o_str(" N"); o_ulong(n); }
}
static void reply_finish(uint8_t numbered, uint16_t n) {
    if (numbered) {
        memcpy(last_reply, out, out_len);
        last_reply_len = out_len;
        last_n = n;
        have_last_n = 1;
    }
    o_send();
}

static void execute(char *body, uint8_t numbered, uint16_t n) {
    char *argv[6];
    uint8_t argc = 0;
    char *p = body;
    uint32_t a = 0, b = 0, c = 0;
    int32_t md;
    while (*p && argc < 6) {
        argv[argc++] = p;
        while (*p && *p != ' ') p++;
        if (*p) *p++ = 0;
    }
    if (*p || argc == 0) goto bad_arg;
#define CMD(name, nargs) (strcmp(argv[0], name) == 0 && ((argc - 1) == (nargs) || ({ goto bad_arg; 0; })))
    if (CMD("ID", 0)) {
        reply_begin(1, 0, numbered, n);
        o_str(" proto=1 name=" FW_NAME " fw=" FW_VERSION);
    } else if (CMD("CAPS", 0)) {
        reply_begin(1, 0, numbered, n);
        o_str(" steps="); o_ulong(STEPS_PER_TURN); o_str(" lights="); o_ulong(LIGHTS);
        o_str(" lasers="); o_ulong(LASERS); o_str(" pwm=1 home=0 trigger=1");
    } else if (CMD("POS", 0)) {
        reply_begin(1, 0, numbered, n);
        o_str(" pos="); o_long(read_pos()); o_str(" moving="); o_ulong(moving ? 1 : 0);
    } else if (strcmp(argv[0], "MOVE") == 0 || strcmp(argv[0], "TURN") == 0) {
        if (argc != 2 || parse_millideg(argv[1], &md)) goto bad_arg;
        if (moving || motion_id) { reply_begin(0, 3, numbered, n); o_str(" busy"); goto send; }
        int32_t to = argv[0][0] == 'M' ? millideg_to_steps(md) : target + millideg_to_steps(md);
        start_motion(to);
        reply_begin(1, 0, numbered, n);
        o_str(" move="); o_ulong(motion_id); o_str(" target="); o_long(to);
    } else if (CMD("HOME", 0)) {
        reply_begin(0, 4, numbered, n); o_str(" no end stop");
    } else if (CMD("ZERO", 0)) {
        if (moving || motion_id) { reply_begin(0, 3, numbered, n); o_str(" busy"); goto send; }
        cli(); pos = 0; target = 0; sei();
        reply_begin(1, 0, numbered, n);
    } else if (CMD("MOTOR", 1)) {
        if (parse_u32(argv[1], 1, &a)) goto bad_arg;
        if (!a && (moving || motion_id)) { reply_begin(0, 3, numbered, n); o_str(" busy"); goto send; }
        set_motor((uint8_t)a);
        reply_begin(1, 0, numbered, n);
    } else if (CMD("LIGHT", 2)) {
        if (parse_u32(argv[1], 255, &a) || parse_u32(argv[2], 255, &b)) goto bad_arg;
        if (a >= LIGHTS) { reply_begin(0, 4, numbered, n); o_str(" no light "); o_ulong(a); goto send; }
        set_light((uint8_t)a, (uint8_t)b);
        reply_begin(1, 0, numbered, n);
    } else if (CMD("LASER", 2)) {
        if (parse_u32(argv[1], 255, &a) || parse_u32(argv[2], 1, &b)) goto bad_arg;
        if (a >= LASERS) { reply_begin(0, 4, numbered, n); o_str(" no laser "); o_ulong(a); goto send; }
        set_laser((uint8_t)a, (uint8_t)b);
        reply_begin(1, 0, numbered, n);
    } else if (CMD("TRIG", 1)) {
        if (parse_u32(argv[1], 1000, &a) || a == 0) goto bad_arg;
        PORTB |= _BV(PB4);
        uint32_t until = now_ms() + a;
        while ((int32_t)(now_ms() - until) < 0) {}
        PORTB &= ~_BV(PB4);
        reply_begin(1, 0, numbered, n);
    } else if (CMD("SAFE", 3)) {
        if (parse_u32(argv[1], 65535, &a) || parse_u32(argv[2], 0xFFFFFFFFUL, &b) || parse_u32(argv[3], 0xFFFFFFFFUL, &c))
            goto bad_arg;
        limit_laser_s = (uint16_t)a; limit_idle_ms = b; limit_watchdog_ms = c;
        reply_begin(1, 0, numbered, n);
    } else if (CMD("OFF", 0)) {
        everything_off();
        reply_begin(1, 0, numbered, n);
    } else {
        reply_begin(0, 1, numbered, n); o_str(" unknown command");
    }
send:
    reply_finish(numbered, n);
    return;
bad_arg:
    reply_begin(0, 2, numbered, n); o_str(" bad argument");
    reply_finish(numbered, n);
}

static void handle_line(void) {
    char *body = line;
    uint8_t i, numbered = 0, had_sum = 0;
    uint16_t n = 0;
    line[line_len] = 0;
    for (i = 0; i < line_len; i++) {
        if ((uint8_t)line[i] < 0x20 || (uint8_t)line[i] > 0x7E) {
            out_len = 0; o_str("error:1 not printable ASCII"); o_send();
            return;
        }
    }
    char *star = strrchr(line, '*');
    if (star) {
        int h = hexval(star[1]), l = star[1] ? hexval(star[2]) : -1;
        uint8_t sum = 0;
        char *q;
        if (h < 0 || l < 0 || star[3]) { out_len = 0; o_str("error:2 bad checksum field"); o_send(); return; }
        for (q = line; q < star; q++) sum ^= (uint8_t)*q;
        if (sum != (uint8_t)(h * 16 + l)) { out_len = 0; o_str("error:5 bad checksum"); o_send(); return; }
        *star = 0;
        had_sum = 1;
        checksum_mode = 1;
    }
    if (body[0] == 'N' && body[1] >= '0' && body[1] <= '9') {
        char *sp = strchr(body, ' ');
        uint32_t v;
        if (sp) {
            *sp = 0;
            if (parse_u32(body + 1, 65535, &v) == 0) {
                numbered = 1;
                n = (uint16_t)v;
                body = sp + 1;
            } else {
                *sp = ' ';
            }
        }
    }
    (void)had_sum;
    if (numbered && have_last_n && n == last_n) {
        /* A resend of the last line: answer again, do not act again. */
        memcpy(out, last_reply, last_reply_len);
        out_len = last_reply_len;
        o_send();
        return;
    }
    execute(body, numbered, n);
}

/* ---- setup ----------------------------------------------------------------------------- */
static void banner(void) {
    out_len = 0;
    o_str("@ready proto=1 name=" FW_NAME " fw=" FW_VERSION);
    o_send();
}
static void soft_reset(void) {
    cli();
    moving = 0; done_pending = 0; pos = 0; target = 0;
    rx_head = rx_tail = 0;
    rt_status = rt_stop = rt_reset = 0;
    sei();
    motion_id = 0; last_move = 0;
    everything_off();
    checksum_mode = 0; have_last_n = 0; line_len = 0; line_overflow = 0;
    limit_laser_s = 255; limit_idle_ms = 10000; limit_watchdog_ms = 0; watchdog_tripped = 0;
    banner();
}

int main(void) {
    DDRD |= _BV(PD2) | _BV(PD3) | _BV(PD4) | _BV(PD5) | _BV(PD6) | _BV(PD7);
    DDRB |= _BV(PB0) | _BV(PB1) | _BV(PB3) | _BV(PB4);
    PORTD |= _BV(PD7); /* driver disabled */
    /* Timer0, Timer2: fast PWM, clk/64; Timer0 overflow counts time. */
    TCCR0A = _BV(WGM01) | _BV(WGM00);
    TCCR0B = _BV(CS01) | _BV(CS00);
    TIMSK0 = _BV(TOIE0);
    TCCR2A = _BV(WGM21) | _BV(WGM20);
    TCCR2B = _BV(CS22);
    /* Timer1: CTC at STEP_RATE, clk/8. */
    TCCR1A = 0;
    TCCR1B = _BV(WGM12) | _BV(CS11);
    OCR1A = (uint16_t)(F_CPU / 8 / STEP_RATE - 1);
    TIMSK1 = _BV(OCIE1A);
    /* UART 115200 8N1, double speed. */
    UCSR0A = _BV(U2X0);
    UBRR0 = (uint16_t)((F_CPU / 8 / 115200) - 1);
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);
    sei();
    soft_reset();

    for (;;) {
        int ch;
        uint32_t t = now_ms();
        if (rt_reset) { soft_reset(); continue; }
        if (rt_stop) {
            rt_stop = 0;
            if (motion_id) { cli(); target = pos; done_pending = 0; sei(); report_end("@stopped"); }
            set_laser(0, 0); set_laser(1, 0);
        }
        if (rt_status) {
            rt_status = 0;
            out_len = 0;
            o_str("@status state="); o_str(moving ? "moving" : "idle");
            o_str(" pos="); o_long(read_pos()); o_str(" move="); o_ulong(last_move);
            o_send();
        }
        if (done_pending) { done_pending = 0; report_end("@done"); }
        while ((ch = rx_get()) >= 0) {
            watchdog_tripped = 0;
            if (ch == '\r') continue;
            if (ch == '\n') {
                if (line_overflow) { out_len = 0; o_str("error:7 line too long"); o_send(); }
                else if (line_len) handle_line();
                line_len = 0; line_overflow = 0;
                break; /* one line per pass, so real-time bytes are served between lines */
            }
            if (line_len < MAX_LINE) line[line_len++] = (char)ch; else line_overflow = 1;
        }
        /* Safety. */
        for (uint8_t i = 0; i < LASERS; i++) {
            if (laser_on[i] && limit_laser_s && t - laser_on_ms[i] >= (uint32_t)limit_laser_s * 1000UL) {
                set_laser(i, 0);
                out_len = 0; o_str("@off laser="); o_ulong(i); o_send();
            }
        }
        if (motor_on && !moving && !motion_id && limit_idle_ms && t - idle_since_ms >= limit_idle_ms) {
            set_motor(0);
            out_len = 0; o_str("@off motor"); o_send();
        }
        if (limit_watchdog_ms && !watchdog_tripped) {
            uint32_t last;
            cli(); last = last_rx_ms; sei();
            last = last + (last >> 6) - (last >> 11);
            if (t - last >= limit_watchdog_ms) {
                everything_off();
                watchdog_tripped = 1;
                out_len = 0; o_str("@off watchdog"); o_send();
            }
        }
    }
}
