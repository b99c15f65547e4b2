/* Servo-rig firmware core: Timer1 software servo pulses, motion, serial protocol, EEPROM.
 *
 * Pins (Arduino Uno / Nano): D9 = PB1 scene servo, D10 = PB2 turntable servo,
 * D8 = PB0 trigger output (1 ms high pulse at the first servo frame of a motion).
 *
 * Timing: Timer1 runs free in normal mode at F_CPU/8 (0.5 us ticks at 16 MHz); its overflow
 * count and TCNT1 give the device clock in microseconds.  The compare-A interrupt walks a
 * three-phase 20 ms frame: at the frame start it raises D9 (and D8 when a motion starts),
 * after the scene pulse it lowers D9 and raises D10, after the turntable pulse it lowers D10
 * and tells the main loop to compute the next frame's pulse widths.  A motion always starts
 * at a frame start, so its commanded angle at frame k is the profile at exactly k * 20 ms.
 * (Timer1 mode 14 hardware PWM is avoided: simavr 1.6 mis-simulates it.)
 */
#include <avr/eeprom.h>
#include <avr/interrupt.h>
#include <avr/pgmspace.h>
#include <avr/io.h>
#include <avr/wdt.h>
#include <string.h>

#include "profile.h"
#include "rig.h"

#ifndef F_CPU
#error "F_CPU must be defined (16000000UL on an Uno / Nano)"
#endif
#if F_CPU != 16000000UL
#error "the servo timing assumes a 16 MHz clock (Timer1 ticks of 0.5 us)"
#endif

#define PIN_TRIGGER PB0
#define PIN_SERVO PB1
#define PIN_TURN PB2
#define TICKS_PER_US 2U

/* ------------------------------------------------------------------ configuration */

#define CONFIG_MAGIC 0x5256u
#define CONFIG_VERSION 1

typedef struct {
    uint16_t magic;
    uint8_t version;
    int32_t min_mdeg, max_mdeg;
    uint16_t max_speed_dps;
    uint16_t pulse_min_us, pulse_max_us;
    int32_t start_mdeg;
    uint8_t nseg;
    rig_segment_t seg[RIG_MAX_SEGMENTS];
    uint8_t sum;
} config_t;

static config_t cfg;
static config_t EEMEM ee_cfg;

static uint8_t config_sum(const config_t *c)
{
    const uint8_t *p = (const uint8_t *)c;
    uint8_t s = 0xA5;
    uint16_t i;
    for (i = 0; i < offsetof(config_t, sum); i++)
        s = (uint8_t)(s + p[i]);
    return s;
}

static void config_defaults(config_t *c)
{
    memset(c, 0, sizeof(*c));
    c->magic = CONFIG_MAGIC;
    c->version = CONFIG_VERSION;
    c->min_mdeg = 0;
    c->max_mdeg = 180000L;
    c->max_speed_dps = 600;
    c->pulse_min_us = 1000;
    c->pulse_max_us = 2000;
    /* DEFAULT_RUN of servo_profile.py: 90 -> 135 -> 45 -> 90 deg in 250 + 500 + 250 ms */
    c->start_mdeg = 90000L;
    c->nseg = 3;
    c->seg[0].angle_mdeg = 135000L; c->seg[0].ms = 250;
    c->seg[1].angle_mdeg = 45000L;  c->seg[1].ms = 500;
    c->seg[2].angle_mdeg = 90000L;  c->seg[2].ms = 250;
}

static uint8_t limits_valid(int32_t lo, int32_t hi, uint16_t speed, uint16_t pmin, uint16_t pmax)
{
    return lo >= 0 && hi <= 180000L && lo < hi && speed >= 1 && speed <= 6000 &&
           pmin >= 400 && pmax <= 2600 && pmin < pmax;
}

static void config_load(void)
{
    eeprom_read_block(&cfg, &ee_cfg, sizeof(cfg));
    if (cfg.magic != CONFIG_MAGIC || cfg.version != CONFIG_VERSION || cfg.sum != config_sum(&cfg) ||
        !limits_valid(cfg.min_mdeg, cfg.max_mdeg, cfg.max_speed_dps, cfg.pulse_min_us,
                      cfg.pulse_max_us) || cfg.nseg < 1 || cfg.nseg > RIG_MAX_SEGMENTS)
        config_defaults(&cfg);
}

/* Returns 0 when a byte does not read back as written (a worn-out cell): the caller then
 * reloads what the EEPROM holds, so RAM never claims settings that a reset would lose. */
static uint8_t config_save(void)
{
    const uint8_t *p = (const uint8_t *)&cfg;
    uint8_t *e = (uint8_t *)&ee_cfg;
    uint16_t i;
    cfg.sum = config_sum(&cfg);
    for (i = 0; i < sizeof(cfg); i++) {   /* only changed bytes are written (3.3 ms each) */
        wdt_reset();
        eeprom_update_byte(e + i, p[i]);
    }
    for (i = 0; i < sizeof(cfg); i++)
        if (eeprom_read_byte(e + i) != p[i])
            return 0;
    return 1;
}

/* ------------------------------------------------------------------ device clock, frames */

static volatile uint32_t t1_overflows;
static volatile uint32_t frame_us;        /* device time (us) of the next frame start */
static volatile uint32_t frame_done_us;   /* start of the frame whose pulses just ended */
static volatile uint8_t frame_flag, frame_phase, trigger_arm;
static volatile uint16_t servo_ticks, turn_ticks;

ISR(TIMER1_OVF_vect) { t1_overflows++; }

static uint32_t micros_now(void)
{
    uint8_t sreg = SREG;
    uint32_t ovf;
    uint16_t t;
    cli();
    ovf = t1_overflows;
    t = TCNT1;
    if ((TIFR1 & _BV(TOV1)) && t < 0x8000u)
        ovf++;
    SREG = sreg;
    return (ovf << 15) | (t >> 1);      /* ticks / 2, modulo 2^32 us */
}

ISR(TIMER1_COMPA_vect)
{
    if (frame_phase == 0) {
        uint16_t base = (uint16_t)(frame_us * TICKS_PER_US);
        if (trigger_arm) {
            PORTB |= _BV(PIN_SERVO) | _BV(PIN_TRIGGER);   /* one write: same cycle */
            OCR1B = base + RIG_TRIGGER_US * TICKS_PER_US;
            TIFR1 = _BV(OCF1B);
            TIMSK1 |= _BV(OCIE1B);
            trigger_arm = 0;
        } else {
            PORTB |= _BV(PIN_SERVO);
        }
        OCR1A = base + servo_ticks;
        frame_phase = 1;
    } else if (frame_phase == 1) {
        PORTB = (uint8_t)((PORTB & ~_BV(PIN_SERVO)) | _BV(PIN_TURN));
        OCR1A += turn_ticks;
        frame_phase = 2;
    } else {
        PORTB &= (uint8_t)~_BV(PIN_TURN);
        frame_done_us = frame_us;
        frame_us += RIG_FRAME_US;
        OCR1A = (uint16_t)(frame_us * TICKS_PER_US);
        frame_phase = 0;
        frame_flag = 1;
    }
}

ISR(TIMER1_COMPB_vect)
{
    PORTB &= (uint8_t)~_BV(PIN_TRIGGER);
    TIMSK1 &= (uint8_t)~_BV(OCIE1B);
}

/* ------------------------------------------------------------------ serial */

#define RX_SIZE 64
#define TX_SIZE 160                 /* the longest reply (GET PROFILE, 8 segments) fits whole */
/* Not a power of two: indices wrap by comparison, never by '%' (a division routine of ~15 us
 * in the transmit interrupt would delay the servo pulse edges). */
#define TX_NEXT(i) ((uint8_t)((i) + 1 == TX_SIZE ? 0 : (i) + 1))
static volatile uint8_t rx_buf[RX_SIZE], rx_head, rx_tail, rx_lost;
/* rx_gap[i] set: bytes were lost (receive buffer full) just before rx_buf[i].  Where the gap
 * lies decides whether the line's tag can still be trusted (see process_line).  A byte per
 * slot, not a bit: the receive interrupt stays short, so the servo pulses keep their timing. */
static volatile uint8_t rx_gap[RX_SIZE];
static volatile uint8_t tx_buf[TX_SIZE], tx_head, tx_tail;

ISR(USART_RX_vect)
{
    uint8_t c = UDR0;
    uint8_t n = (uint8_t)((rx_head + 1) % RX_SIZE);
    if (n != rx_tail) {
        uint8_t h = rx_head;
        rx_gap[h] = rx_lost;
        rx_lost = 0;
        rx_buf[h] = c;
        rx_head = n;
    } else {
        rx_lost = 1;
    }
}

ISR(USART_UDRE_vect)
{
    if (tx_head == tx_tail) {
        UCSR0B &= (uint8_t)~_BV(UDRIE0);
        return;
    }
    UDR0 = tx_buf[tx_tail];
    tx_tail = TX_NEXT(tx_tail);
}

static void out_c(char c)
{
    uint8_t n = TX_NEXT(tx_head);
    while (n == tx_tail)            /* the UART drains at 115200 whether or not a host listens */
        wdt_reset();
    tx_buf[tx_head] = (uint8_t)c;
    tx_head = n;
    cli();
    UCSR0B |= _BV(UDRIE0);
    sei();
}

static void out_s(const char *s)
{
    while (*s)
        out_c(*s++);
}

static void out_P(const char *p)   /* a string in flash (PSTR) */
{
    char c;
    while ((c = (char)pgm_read_byte(p++)))
        out_c(c);
}

static void out_u32(uint32_t v)
{
    char b[11];
    uint8_t i = 0;
    do {
        b[i++] = (char)('0' + v % 10);
        v /= 10;
    } while (v);
    while (i)
        out_c(b[--i]);
}

static void out_deg(int32_t mdeg)    /* millidegrees as decimal degrees, trailing zeros cut */
{
    uint16_t frac;
    if (mdeg < 0) {
        out_c('-');
        mdeg = -mdeg;
    }
    out_u32((uint32_t)mdeg / 1000);
    frac = (uint16_t)((uint32_t)mdeg % 1000);
    if (frac) {
        out_c('.');
        out_c((char)('0' + frac / 100));
        frac %= 100;
        if (frac) {
            out_c((char)('0' + frac / 10));
            frac %= 10;
            if (frac)
                out_c((char)('0' + frac));
        }
    }
}

/* ------------------------------------------------------------------ motion */

enum { M_IDLE = 0, M_PENDING, M_ARMED, M_ACTIVE, M_FINISHING };
enum { K_MOVE = 0, K_RUN, K_HOME, K_TURN };
static const char *const kind_name[] = {"MOVE", "RUN", "HOME", "TURN"};

typedef struct {
    uint8_t state, kind;
    uint32_t t_start, t_done;
    int32_t a0, cur;
    uint8_t nseg;
    rig_segment_t seg[RIG_MAX_SEGMENTS];
} motion_t;

static motion_t servo, turn;

static void report(const char *what, const motion_t *m, uint32_t t)
{
    out_P(what);
    out_c(' ');
    out_s(kind_name[m->kind]);
    out_c(' ');
    out_u32(t);
}

/* Called once per frame, after the frame that started at frame_done_us has been output. */
static void motion_frame(motion_t *m, uint32_t done, uint32_t next, uint8_t is_servo)
{
    if (m->state == M_ARMED && (int32_t)(done - m->t_start) >= 0) {
        report(PSTR("START"), m, m->t_start);
        out_c('\n');
        m->state = M_ACTIVE;
    }
    if (m->state == M_FINISHING && (int32_t)(done - m->t_done) >= 0) {
        report(PSTR("DONE"), m, m->t_done);
        out_c('\n');
        m->state = M_IDLE;
    }
    if (m->state == M_PENDING) {
        m->t_start = next;
        m->state = M_ARMED;
        if (is_servo)
            trigger_arm = 1;      /* read by the ISR at the start of frame `next` */
    }
    if (m->state == M_ARMED || m->state == M_ACTIVE) {
        uint8_t finished;
        m->cur = rig_profile_command_mdeg(next - m->t_start, m->a0, m->seg, m->nseg, &finished);
        if (finished) {
            m->t_done = next;
            m->state = M_FINISHING;
        }
    }
}

static void frames_update(void)
{
    uint32_t done, next;
    uint16_t s, t;
    cli();
    done = frame_done_us;
    next = frame_us;
    frame_flag = 0;
    sei();
    motion_frame(&servo, done, next, 1);
    motion_frame(&turn, done, next, 0);
    s = rig_pulse_ticks(servo.cur, cfg.pulse_min_us, cfg.pulse_max_us);
    t = rig_pulse_ticks(turn.cur, cfg.pulse_min_us, cfg.pulse_max_us);
    cli();
    servo_ticks = s;
    turn_ticks = t;
    sei();
}

/* ------------------------------------------------------------------ command parsing */

#define MAX_TOKENS 20
static char line[RIG_MAX_LINE + 1];
static uint8_t line_len, line_too_long, line_bad_char, line_lost;
static uint8_t has_seq;
static uint32_t seq;

static uint8_t parse_u32(const char *s, uint32_t max, uint32_t *out)
{
    uint32_t v = 0;
    if (!*s)
        return 0;
    for (; *s; s++) {
        if (*s < '0' || *s > '9')
            return 0;
        if (v > (max - (uint32_t)(*s - '0')) / 10)
            return 0;
        v = v * 10 + (uint32_t)(*s - '0');
    }
    *out = v;
    return 1;
}

/* decimal degrees with at most 3 decimals, |x| <= 1000 deg, to millidegrees */
static uint8_t parse_mdeg(const char *s, int32_t *out)
{
    uint8_t neg = 0, digits = 0, decimals = 0, dot = 0;
    int32_t v = 0;
    if (*s == '-' || *s == '+') {
        neg = *s == '-';
        s++;
    }
    for (; *s; s++) {
        if (*s == '.' && !dot) {
            dot = 1;
            continue;
        }
        if (*s < '0' || *s > '9')
            return 0;
        if (dot && ++decimals > 3)
            return 0;
        if (!dot && ++digits > 4)
            return 0;
        v = v * 10 + (*s - '0');
    }
    if (!digits && !decimals)
        return 0;
    while (decimals++ < 3)
        v *= 10;
    *out = neg ? -v : v;
    return 1;
}

static void reply_head(const char *status)
{
    if (has_seq) {
        out_c('@');
        out_u32(seq);
        out_c(' ');
    }
    out_P(status);
}

static void reply_ok_P(const char *what)          /* what: PSTR */
{
    reply_head(PSTR("OK "));
    out_P(what);
}

static void reply_err(const char *code, const char *reason)   /* both PSTR */
{
    reply_head(PSTR("ERR "));
    out_P(code);
    out_c(' ');
    out_P(reason);
    out_c('\n');
}

/* Stores cfg in EEPROM; when it does not read back, answers ERR EEPROM and returns 0 with
 * cfg reloaded from what the EEPROM holds (what the next reset would give). */
static uint8_t store_config(void)
{
    if (config_save())
        return 1;
    config_load();
    reply_err(PSTR("EEPROM"), PSTR("EEPROM write did not read back (worn-out cell?); settings not stored"));
    return 0;
}

static uint8_t too_fast(int32_t a0, int32_t a1, uint16_t ms)
{
    /* peak speed of a minimum-jerk move is 15/8 |a1 - a0| / D */
    uint32_t delta = (uint32_t)(a1 > a0 ? a1 - a0 : a0 - a1);
    return 15UL * delta > 8UL * cfg.max_speed_dps * ms;
}

static uint8_t in_limits(int32_t mdeg) { return mdeg >= cfg.min_mdeg && mdeg <= cfg.max_mdeg; }

static uint8_t check_target(int32_t a0, int32_t a1, uint16_t ms)
{
    if (!in_limits(a1)) {
        reply_err(PSTR("OUT_OF_RANGE"), PSTR("angle outside the limits (GET LIMITS)"));
        return 0;
    }
    if (too_fast(a0, a1, ms)) {
        reply_err(PSTR("TOO_FAST"), PSTR("peak speed 1.875*|delta|/duration over the speed limit"));
        return 0;
    }
    return 1;
}

static uint8_t parse_duration(const char *s, uint16_t *ms)
{
    uint32_t v;
    if (!parse_u32(s, 65535UL, &v) || v < 1)
        return 0;
    *ms = (uint16_t)v;
    return 1;
}

static void start_motion(motion_t *m, uint8_t kind, uint8_t nseg, const rig_segment_t *seg)
{
    m->kind = kind;
    m->a0 = m->cur;
    m->nseg = nseg;
    memcpy(m->seg, seg, nseg * sizeof(rig_segment_t));
    m->state = M_PENDING;     /* starts at the next frame start; see motion_frame */
    reply_head(PSTR("OK "));
    out_s(kind_name[kind]);
    out_c('\n');
}

static void stop_motion(motion_t *m)
{
    if (m->state == M_IDLE)
        return;
    if (m->state == M_PENDING) {
        m->state = M_IDLE;    /* never started: nothing to report, nothing moved */
        return;
    }
    report(PSTR("STOPPED"), m, micros_now());
    out_c(' ');
    out_deg(m->cur);
    out_c('\n');
    m->state = M_IDLE;
}

static void out_limits(void)
{
    out_c(' ');
    out_deg(cfg.min_mdeg);
    out_c(' ');
    out_deg(cfg.max_mdeg);
    out_c(' ');
    out_u32(cfg.max_speed_dps);
    out_c(' ');
    out_u32(cfg.pulse_min_us);
    out_c(' ');
    out_u32(cfg.pulse_max_us);
    out_c('\n');
}

static void out_profile(void)
{
    uint8_t k;
    out_c(' ');
    out_deg(cfg.start_mdeg);
    for (k = 0; k < cfg.nseg; k++) {
        out_c(' ');
        out_deg(cfg.seg[k].angle_mdeg);
        out_c(' ');
        out_u32(cfg.seg[k].ms);
    }
    out_c('\n');
}

static const char *state_name(const motion_t *m)
{
    return m->state == M_IDLE ? "IDLE" : kind_name[m->kind];
}

static void execute(char **tok, uint8_t n)
{
    const char *c = tok[0];
    uint8_t busy = servo.state != M_IDLE;

    if (!strcmp_P(c, PSTR("HELLO"))) {
        if (n != 1) { reply_err(PSTR("BAD_ARGUMENT"), PSTR("HELLO takes no argument")); return; }
        reply_ok_P(PSTR("HELLO rig_servo proto="));
        out_u32(RIG_PROTOCOL_VERSION);
        out_P(PSTR(" fw=" RIG_FIRMWARE_VERSION " frame_us="));
        out_u32(RIG_FRAME_US);
        out_P(PSTR(" trigger_us="));
        out_u32(RIG_TRIGGER_US);
        out_c('\n');
    } else if (!strcmp_P(c, PSTR("PING"))) {
        uint32_t now = micros_now();
        if (n > 2) { reply_err(PSTR("BAD_ARGUMENT"), PSTR("usage: PING [token]")); return; }
        reply_ok_P(PSTR("PONG "));
        out_u32(now);
        if (n == 2) {
            out_c(' ');
            out_s(tok[1]);
        }
        out_c('\n');
    } else if (!strcmp_P(c, PSTR("STATUS"))) {
        reply_ok_P(PSTR("STATUS "));
        out_deg(servo.cur);
        out_c(' ');
        out_deg(turn.cur);
        out_c(' ');
        out_s(state_name(&servo));
        out_c(' ');
        out_s(state_name(&turn));
        out_c('\n');
    } else if (!strcmp_P(c, PSTR("MOVE")) || !strcmp_P(c, PSTR("TURN"))) {
        uint8_t is_turn = c[0] == 'T';
        motion_t *m = is_turn ? &turn : &servo;
        rig_segment_t s;
        int32_t a;
        if (n != 3 || !parse_mdeg(tok[1], &a) || !parse_duration(tok[2], &s.ms)) {
            reply_err(PSTR("BAD_ARGUMENT"), is_turn ? PSTR("usage: TURN <deg> <ms 1..65535>")
                                              : PSTR("usage: MOVE <deg> <ms 1..65535>"));
            return;
        }
        if (m->state != M_IDLE) { reply_err(PSTR("BUSY"), PSTR("a motion is running; STOP first")); return; }
        if (is_turn) {
            if (a < 0 || a > 180000L) { reply_err(PSTR("OUT_OF_RANGE"), PSTR("turntable angle 0..180")); return; }
        } else if (!check_target(servo.cur, a, s.ms)) {
            return;
        }
        s.angle_mdeg = a;
        start_motion(m, is_turn ? K_TURN : K_MOVE, 1, &s);
    } else if (!strcmp_P(c, PSTR("HOME"))) {
        rig_segment_t s;
        s.ms = 1000;
        if (n > 2 || (n == 2 && !parse_duration(tok[1], &s.ms))) {
            reply_err(PSTR("BAD_ARGUMENT"), PSTR("usage: HOME [ms 1..65535]"));
            return;
        }
        if (busy) { reply_err(PSTR("BUSY"), PSTR("a motion is running; STOP first")); return; }
        s.angle_mdeg = cfg.start_mdeg;
        if (!check_target(servo.cur, s.angle_mdeg, s.ms))
            return;
        start_motion(&servo, K_HOME, 1, &s);
    } else if (!strcmp_P(c, PSTR("RUN"))) {
        uint8_t k;
        int32_t a0 = cfg.start_mdeg;
        if (n != 1) { reply_err(PSTR("BAD_ARGUMENT"), PSTR("RUN takes no argument")); return; }
        if (busy) { reply_err(PSTR("BUSY"), PSTR("a motion is running; STOP first")); return; }
        if (servo.cur != cfg.start_mdeg) { reply_err(PSTR("NOT_HOME"), PSTR("servo is not at the profile start; send HOME")); return; }
        for (k = 0; k < cfg.nseg; k++) {
            if (!in_limits(cfg.seg[k].angle_mdeg) || !in_limits(a0) ||
                too_fast(a0, cfg.seg[k].angle_mdeg, cfg.seg[k].ms)) {
                reply_err(PSTR("PROFILE_LIMITS"), PSTR("the stored profile breaks the angle or speed limits"));
                return;
            }
            a0 = cfg.seg[k].angle_mdeg;
        }
        start_motion(&servo, K_RUN, cfg.nseg, cfg.seg);
    } else if (!strcmp_P(c, PSTR("STOP"))) {
        if (n != 1) { reply_err(PSTR("BAD_ARGUMENT"), PSTR("STOP takes no argument")); return; }
        reply_ok_P(PSTR("STOP\n"));
        stop_motion(&servo);
        stop_motion(&turn);
    } else if (!strcmp_P(c, PSTR("GET")) && n == 2 && !strcmp_P(tok[1], PSTR("LIMITS"))) {
        reply_ok_P(PSTR("LIMITS"));
        out_limits();
    } else if (!strcmp_P(c, PSTR("GET")) && n == 2 && !strcmp_P(tok[1], PSTR("PROFILE"))) {
        reply_ok_P(PSTR("PROFILE"));
        out_profile();
    } else if (!strcmp_P(c, PSTR("SET")) && n >= 2 && !strcmp_P(tok[1], PSTR("LIMITS"))) {
        int32_t lo, hi;
        uint32_t sp, pmin, pmax;
        if (n != 7 || !parse_mdeg(tok[2], &lo) || !parse_mdeg(tok[3], &hi) ||
            !parse_u32(tok[4], 65535UL, &sp) || !parse_u32(tok[5], 65535UL, &pmin) ||
            !parse_u32(tok[6], 65535UL, &pmax)) {
            reply_err(PSTR("BAD_ARGUMENT"), PSTR("usage: SET LIMITS <min_deg> <max_deg> <max_speed_dps> <pulse_min_us> <pulse_max_us>"));
            return;
        }
        if (!limits_valid(lo, hi, (uint16_t)sp, (uint16_t)pmin, (uint16_t)pmax)) {
            reply_err(PSTR("OUT_OF_RANGE"), PSTR("need 0<=min<max<=180, speed 1..6000, 400<=pulse_min<pulse_max<=2600"));
            return;
        }
        if (busy || turn.state != M_IDLE) { reply_err(PSTR("BUSY"), PSTR("a motion is running; STOP first")); return; }
        cfg.min_mdeg = lo;
        cfg.max_mdeg = hi;
        cfg.max_speed_dps = (uint16_t)sp;
        cfg.pulse_min_us = (uint16_t)pmin;
        cfg.pulse_max_us = (uint16_t)pmax;
        if (!store_config())
            return;
        reply_ok_P(PSTR("LIMITS"));
        out_limits();
    } else if (!strcmp_P(c, PSTR("SET")) && n >= 2 && !strcmp_P(tok[1], PSTR("PROFILE"))) {
        rig_segment_t seg[RIG_MAX_SEGMENTS];
        int32_t start;
        uint8_t k, nseg = (uint8_t)((n - 3) / 2);
        if (n < 5 || (n - 3) % 2 || nseg > RIG_MAX_SEGMENTS || !parse_mdeg(tok[2], &start) ||
            start < 0 || start > 180000L) {
            reply_err(PSTR("BAD_ARGUMENT"), PSTR("usage: SET PROFILE <start_deg> <deg> <ms> [<deg> <ms> ...] (1..8 segments, 0..180 deg)"));
            return;
        }
        for (k = 0; k < nseg; k++) {
            if (!parse_mdeg(tok[3 + 2 * k], &seg[k].angle_mdeg) || seg[k].angle_mdeg < 0 ||
                seg[k].angle_mdeg > 180000L || !parse_duration(tok[4 + 2 * k], &seg[k].ms)) {
                reply_err(PSTR("BAD_ARGUMENT"), PSTR("segment angles 0..180 deg (3 decimals), durations 1..65535 ms"));
                return;
            }
        }
        if (busy) { reply_err(PSTR("BUSY"), PSTR("a motion is running; STOP first")); return; }
        cfg.start_mdeg = start;
        cfg.nseg = nseg;
        memcpy(cfg.seg, seg, sizeof(seg));
        if (!store_config())
            return;
        reply_ok_P(PSTR("PROFILE"));
        out_profile();
    } else if (!strcmp_P(c, PSTR("FACTORY"))) {
        if (busy || turn.state != M_IDLE) { reply_err(PSTR("BUSY"), PSTR("a motion is running; STOP first")); return; }
        config_defaults(&cfg);
        if (!store_config())
            return;
        reply_ok_P(PSTR("FACTORY\n"));
    } else if (!strcmp_P(c, PSTR("REBOOT"))) {
        reply_ok_P(PSTR("REBOOT\n"));
        while (tx_head != tx_tail)
            wdt_reset();
        wdt_enable(WDTO_15MS);
        for (;;) {}                   /* the watchdog resets the chip */
    } else if (!strcmp_P(c, PSTR("GET")) || !strcmp_P(c, PSTR("SET"))) {
        reply_err(PSTR("BAD_ARGUMENT"), PSTR("usage: GET|SET LIMITS|PROFILE ..."));
    } else {
        reply_err(PSTR("UNKNOWN_COMMAND"), PSTR("try HELLO, PING, MOVE, RUN, HOME, STOP, TURN, STATUS, GET, SET"));
    }
}

/* Reads a leading "@<n>" tag into seq / has_seq and returns where the command starts; NULL
 * when the line starts with '@' but no valid tag follows (digits only, 0..4294967295, then a
 * space, a tab or the end): such a line is answered untagged (PROTOCOL.md, "Tags"). */
static char *parse_tag(char *p)
{
    char *q, end;
    uint8_t ok;
    while (*p == ' ' || *p == '\t')
        p++;
    if (*p != '@')
        return p;
    for (q = p + 1; *q && *q != ' ' && *q != '\t'; q++) {}
    end = *q;
    *q = 0;
    ok = parse_u32(p + 1, 0xFFFFFFFFUL, &seq);
    *q = end;
    if (!ok)
        return NULL;
    has_seq = 1;
    return q;
}

/* Every reply to a line whose tag can be read carries that tag, errors included; the tag is
 * read first, before anything else about the line is judged. */
static void process_line(void)
{
    char *tok[MAX_TOKENS];
    uint8_t n = 0;
    char *p, *cmd;
    line[line_len] = 0;
    has_seq = 0;
    p = parse_tag(line);
    if (!p) {
        reply_err(PSTR("BAD_TAG"), line_lost ? PSTR("tag unreadable: receive buffer overflowed; line ignored")
                                   : line_bad_char ? PSTR("tag unreadable: non-printable byte; line ignored")
                                   : PSTR("a tag is @<0..4294967295> then a space; line ignored"));
        return;
    }
    if (line_lost) {
        reply_err(PSTR("RX_OVERFLOW"), PSTR("receive buffer overflowed, bytes lost; wait for each reply; line ignored"));
        return;
    }
    if (line_too_long) {
        reply_err(PSTR("LINE_TOO_LONG"), PSTR("lines are at most 160 characters; line ignored"));
        return;
    }
    if (line_bad_char) {
        reply_err(PSTR("BAD_CHARACTER"), PSTR("non-printable byte in line; line ignored"));
        return;
    }
    for (cmd = p; *p; p++)            /* upper-case the command */
        if (*p >= 'a' && *p <= 'z')
            *p = (char)(*p - 'a' + 'A');
    p = cmd;
    while (*p) {
        while (*p == ' ' || *p == '\t')
            *p++ = 0;
        if (!*p)
            break;
        if (n == MAX_TOKENS) {
            reply_err(PSTR("BAD_ARGUMENT"), PSTR("too many arguments"));
            return;
        }
        tok[n++] = p;
        while (*p && *p != ' ' && *p != '\t')
            p++;
    }
    if (!n) {
        if (has_seq)
            reply_err(PSTR("BAD_ARGUMENT"), PSTR("empty command"));
        return;                       /* blank lines are ignored */
    }
    execute(tok, n);
}

/* A byte that cannot be kept (non-printable) or bytes that were lost leave a '?' in the line,
 * so that a tag they cut through no longer reads as a valid tag. */
static void line_put(char c)
{
    if (line_len >= RIG_MAX_LINE)
        line_too_long = 1;
    else
        line[line_len++] = c;
}

static void serial_poll(void)
{
    while (rx_tail != rx_head) {
        uint8_t i = rx_tail;
        uint8_t c = rx_buf[i];
        uint8_t gap = rx_gap[i];
        rx_tail = (uint8_t)((i + 1) % RX_SIZE);
        if (gap) {
            line_lost = 1;
            line_put('?');
        }
        if (c == '\n') {
            process_line();
            line_len = line_too_long = line_bad_char = line_lost = 0;
        } else if (c == '\r') {
            continue;
        } else if (c < 0x20 || c > 0x7e) {
            line_bad_char = 1;
            line_put('?');
        } else {
            line_put((char)c);
        }
        if (frame_flag)               /* a long line never delays the next frame's pulses */
            frames_update();
    }
}

/* ------------------------------------------------------------------ entry points */

void rig_setup(void)
{
    uint8_t reset_cause = MCUSR;
    MCUSR = 0;
    wdt_disable();                    /* first thing: a watchdog reset leaves it running */
    cli();
    config_load();
    servo.cur = cfg.start_mdeg;       /* the servo is driven to the profile start at power-up */
    turn.cur = 90000L;
    servo_ticks = rig_pulse_ticks(servo.cur, cfg.pulse_min_us, cfg.pulse_max_us);
    turn_ticks = rig_pulse_ticks(turn.cur, cfg.pulse_min_us, cfg.pulse_max_us);

    DDRB |= _BV(PIN_TRIGGER) | _BV(PIN_SERVO) | _BV(PIN_TURN);
    PORTB &= (uint8_t)~(_BV(PIN_TRIGGER) | _BV(PIN_SERVO) | _BV(PIN_TURN));

    TCCR1A = 0;                       /* normal mode */
    TCCR1B = 0;
    TCNT1 = 0;
    t1_overflows = 0;
    frame_us = RIG_FRAME_US;
    frame_phase = 0;
    OCR1A = (uint16_t)(RIG_FRAME_US * TICKS_PER_US);
    TIFR1 = _BV(OCF1A) | _BV(OCF1B) | _BV(TOV1);
    TIMSK1 = _BV(OCIE1A) | _BV(TOIE1);
    TCCR1B = _BV(CS11);               /* clk/8: 0.5 us ticks */

    UCSR0A = _BV(U2X0);               /* 115200 baud at 16 MHz: UBRR 16, U2X */
    UBRR0 = (uint16_t)((F_CPU / 8UL + 115200UL / 2) / 115200UL - 1);
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
    sei();

    wdt_enable(WDTO_250MS);
    out_P(PSTR("BOOT rig_servo proto="));
    out_u32(RIG_PROTOCOL_VERSION);
    out_P(PSTR(" reset="));
    out_u32(reset_cause);
    out_c('\n');
}

void rig_loop(void)
{
    wdt_reset();
    serial_poll();
    if (frame_flag)
        frames_update();
}
