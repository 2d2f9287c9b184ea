/*
 * servo_controller.ino — reference firmware of a slave arm's joint-servo controller (telesurg).
 *
 * Drives up to 8 hobby servos (standard 50 Hz PWM servos, optionally with an analog position
 * feedback wire) from joint position setpoints sent by slave_control's "serial" backend, and
 * streams the joints' state back. The protocol is specified byte by byte in
 * shared/servo_protocol.py (module docstring) and docs/hardware.md; in short:
 *
 *   wire   = COBS(raw) 0x00
 *   raw    = version(1) kind(u8) seq(u16 LE) body(MessagePack map) CRC-16/CCITT-FALSE(u16 LE)
 *   kinds  0x21 HELLO    {"proto","model","fw","joints","lower","upper","max_velocity","rate_hz"}
 *          0x22 STATE    {"t_us","q","qd","current","fault","last_seq_applied",
 *                         "watchdog_tripped","enabled"}
 *          0x30 HELLO_REQUEST (host -> controller): answered with a HELLO
 *          0x31 ENABLE   {"seq"}: clear faults whose cause is gone, hold, follow SETPOINTs
 *          0x32 DISABLE  {}: hold where you are, stop following
 *          0x33 SETPOINT {"seq","q","timeout_ms"}
 *
 * Safety behaviour (the host relies on it):
 *   - boots DISABLED; joints never move before an ENABLE and a SETPOINT;
 *   - a SETPOINT outside LOWER/UPPER or with the wrong joint count sets FAULT_SETPOINT and stops;
 *   - its own watchdog: once a SETPOINT has been applied, if no newer one arrives within that
 *     SETPOINT's timeout_ms, the joints hold where they are, watchdog_tripped is set and the
 *     controller disables (until the next ENABLE) — the arm stops even if the host dies;
 *   - the e-stop input (normally closed to GND) open -> FAULT_ESTOP, servos released;
 *   - faults are latched until an ENABLE finds their cause gone.
 *
 * "Hold" means: keep sending the servos their current pulse (a hobby servo then holds its
 * position against load). Set RELEASE_ON_HOLD to true to detach them instead (limp joints: only
 * for arms that cannot fall).
 *
 * Position measurement: a plain hobby servo reports nothing, so without a feedback pin the STATE's
 * "q" is the position the servo is commanded to (after this sketch's rate limit and the servo's
 * pulse range). With FB_PIN set (servos with an analog feedback wire, e.g. Adafruit 1404), "q" is
 * measured, a joint that cannot follow raises FAULT_FOLLOWING, and the host's MuJoCo shadow can
 * see a stuck or slipping joint. "current" is 0.0 (no current sensing in this reference).
 *
 * The HELLO must describe the robot the host expects (shared/robots.py): MODEL, JOINTS and the
 * joint limits LOWER/UPPER equal to the profile within 1e-4 rad, or the host refuses to send
 * anything. MAX_VELOCITY may be lower than the profile's: the host then rate-limits its setpoints
 * to it. The defaults below describe the mh3f profile (MOTOMAN-MH3F limits) on a 6-servo arm.
 *
 * Board: Arduino Mega 2560 (Uno works for <= 6 joints). Library: Servo (bundled with the IDE).
 * Not compiled in CI; keep it in step with shared/servo_protocol.py (PROTO_VERSION).
 *
 * Link budget: a 6-joint STATE is 181 bytes on the wire (float32 reals), a 6-joint SETPOINT from
 * the host 89 bytes. At 500000 bit/s (exact on a 16 MHz AVR: host serial_baud = 500000) 100 STATEs
 * and 100 SETPOINTs per second use 36 % and 18 % of the two directions. Frames are written in
 * pieces that fit the UART buffer, so the loop never blocks and never misses incoming bytes.
 */

#include <Servo.h>
#include <math.h>
#include <string.h>

// ------------------------------------------------------------------------------ configuration

static const uint32_t BAUD = 500000;     // bit/s; host: serial_baud
static const uint16_t STATE_HZ = 100;    // STATE rate, Hz (HELLO "rate_hz")
static const char MODEL[] = "mh3f";      // robot model (shared/robots.py); host: model
static const char FW[] = "0.1.0";
static const uint8_t JOINTS = 6;         // <= MAX_J
static const bool RELEASE_ON_HOLD = false;

// Joint limits, rad (m for a prismatic joint): the host's profile, else it refuses the controller.
// mh3f: (-160, -85, -105, -170, -120, -360) .. (160, 90, 260, 170, 120, 360) degrees.
static const float LOWER[JOINTS] = {-2.7925268f, -1.4835299f, -1.8325957f, -2.9670597f, -2.0943951f, -6.2831853f};
static const float UPPER[JOINTS] = {2.7925268f, 1.5707963f, 4.5378561f, 2.9670597f, 2.0943951f, 6.2831853f};
// Joint speed limits, rad/s: what the servos manage under load (a standard servo: ~0.2 s/60°
// unloaded = 5 rad/s). The sketch moves each servo's pulse toward its target no faster.
static const float MAX_VELOCITY[JOINTS] = {2.0f, 2.0f, 2.0f, 2.0f, 2.0f, 2.0f};
// Where the joints are at power-up (no feedback: assumed; the profile's home pose).
static const float HOME[JOINTS] = {0.0f, 0.2f, 0.3f, 0.0f, -0.6f, 0.0f};

// Servo wiring and calibration, per joint. pulse_us = CENTER_US + US_PER_RAD * q, clipped to
// [MIN_US, MAX_US] (the servo's travel). A standard servo turns ~90° per 1000 µs:
// US_PER_RAD = 1000 / (π/2) = 636.6; a negative value reverses the joint. Calibrate CENTER_US so
// the joint is at its kinematic zero, and the sign so it turns the positive way (docs/hardware.md).
static const uint8_t SERVO_PIN[JOINTS] = {2, 3, 4, 5, 6, 7};
static const int16_t CENTER_US[JOINTS] = {1500, 1500, 1500, 1500, 1500, 1500};
static const float US_PER_RAD[JOINTS] = {636.6f, 636.6f, -636.6f, 636.6f, 636.6f, 636.6f};
static const int16_t MIN_US[JOINTS] = {600, 600, 600, 600, 600, 600};
static const int16_t MAX_US[JOINTS] = {2400, 2400, 2400, 2400, 2400, 2400};

// Optional analog position feedback: ADC pin or -1. q = (adc - FB_ZERO) * FB_RAD_PER_COUNT.
static const int8_t FB_PIN[JOINTS] = {-1, -1, -1, -1, -1, -1};
static const float FB_ZERO[JOINTS] = {512, 512, 512, 512, 512, 512};
static const float FB_RAD_PER_COUNT[JOINTS] = {0.0046f, 0.0046f, 0.0046f, 0.0046f, 0.0046f, 0.0046f};
static const float FOLLOW_ERROR_RAD = 0.25f;   // with feedback: |measured - commanded| above this ...
static const uint16_t FOLLOW_ERROR_MS = 300;   // ... for this long -> FAULT_FOLLOWING

static const uint8_t PIN_ESTOP = 30;  // normally-closed e-stop chain to GND (INPUT_PULLUP): HIGH = open

// ------------------------------------------------------------------------------ protocol constants

static const uint8_t MAX_J = 8;
static const uint8_t FRAME_VERSION = 1;
static const uint8_t PROTO_VERSION = 1;
static const uint8_t KIND_HELLO = 0x21;
static const uint8_t KIND_STATE = 0x22;
static const uint8_t KIND_HELLO_REQUEST = 0x30;
static const uint8_t KIND_ENABLE = 0x31;
static const uint8_t KIND_DISABLE = 0x32;
static const uint8_t KIND_SETPOINT = 0x33;
static const uint8_t FAULT_ESTOP = 0x01;
static const uint8_t FAULT_FOLLOWING = 0x04;
static const uint8_t FAULT_SETPOINT = 0x20;
static const uint16_t MAX_TIMEOUT_MS = 10000;

// ------------------------------------------------------------------------------ state

static Servo servo[JOINTS];
static bool attached = false;
static float target[JOINTS];         // where each joint should go, rad
static float q_cmd[JOINTS];          // where each servo is commanded now (rate-limited), rad
static float q_meas[JOINTS];         // measured (or, without feedback, commanded) position, rad
static float qd_meas[JOINTS];        // rad/s
static uint32_t follow_bad_since[JOINTS];
static bool enabled = false;
static bool tripped = false;          // watchdog_tripped
static uint8_t faults = 0;            // latched fault bits
static uint32_t last_seq_applied = 0;
static bool wd_armed = false;         // a SETPOINT was applied since the last ENABLE
static uint32_t wd_last_ms = 0, wd_timeout_ms = 0;
static uint16_t seq = 0;              // frame counter, every frame this controller writes
static uint32_t last_move_us = 0, next_state_us = 0, last_meas_us = 0;
static bool hello_pending = false;

static uint8_t rx[256];               // one incoming COBS frame (a 16-joint SETPOINT fits)
static uint16_t rx_len = 0;
static bool rx_overflow = false;

static uint8_t raw[256];              // the frame being built
static uint8_t tx[260];               // COBS frame + 0x00 being written
static uint16_t tx_len = 0, tx_pos = 0;

// ------------------------------------------------------------------------------ CRC and COBS

// CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, not reflected, xorout 0; crc("123456789") = 0x29B1.
static uint16_t crc16(const uint8_t *d, uint16_t n) {
  uint16_t crc = 0xFFFF;
  while (n--) {
    crc ^= (uint16_t)(*d++) << 8;
    for (uint8_t i = 0; i < 8; ++i) crc = (crc & 0x8000) ? (uint16_t)((crc << 1) ^ 0x1021) : (uint16_t)(crc << 1);
  }
  return crc;
}

// COBS-encode n bytes into out (n + n/254 + 1 bytes); returns the encoded length.
static uint16_t cobsEncode(const uint8_t *in, uint16_t n, uint8_t *out) {
  uint16_t code_at = 0, o = 1;
  uint8_t code = 1;
  for (uint16_t i = 0; i < n; ++i) {
    if (in[i] == 0) {
      out[code_at] = code;
      code_at = o++;
      code = 1;
    } else {
      out[o++] = in[i];
      if (++code == 0xFF) {  // a full block of 254 data bytes
        out[code_at] = code;
        code_at = o++;
        code = 1;
      }
    }
  }
  out[code_at] = code;
  return o;
}

// COBS-decode n bytes (no 0x00 inside) into out (capacity cap); returns the length, -1 if bad.
static int16_t cobsDecode(const uint8_t *in, uint16_t n, uint8_t *out, uint16_t cap) {
  uint16_t i = 0, o = 0;
  while (i < n) {
    uint8_t code = in[i++];
    if (code == 0) return -1;
    for (uint8_t k = 1; k < code; ++k) {
      if (i >= n || o >= cap) return -1;
      out[o++] = in[i++];
    }
    if (code != 0xFF && i < n) {
      if (o >= cap) return -1;
      out[o++] = 0;
    }
  }
  return (int16_t)o;
}

// ------------------------------------------------------------------------------ MessagePack writer
// Only what HELLO and STATE need: fixmap, fixarray, fixstr, unsigned integers, float32, bool.
// MessagePack is big-endian.

struct Buf {
  uint8_t *p;
  uint16_t n, cap;
  bool ok;
};

static void put(Buf &b, uint8_t v) {
  if (b.n < b.cap) b.p[b.n++] = v;
  else b.ok = false;
}

static void putBE(Buf &b, uint32_t v, uint8_t bytes) {
  for (int8_t i = bytes - 1; i >= 0; --i) put(b, (uint8_t)(v >> (8 * i)));
}

static void mpMap(Buf &b, uint8_t n) { put(b, 0x80 | n); }    // n <= 15
static void mpArray(Buf &b, uint8_t n) { put(b, 0x90 | n); }  // n <= 15
static void mpBool(Buf &b, bool v) { put(b, v ? 0xC3 : 0xC2); }

static void mpStr(Buf &b, const char *s) {  // fixstr: up to 31 bytes
  uint8_t n = (uint8_t)strlen(s);
  put(b, 0xA0 | n);
  for (uint8_t i = 0; i < n; ++i) put(b, (uint8_t)s[i]);
}

static void mpUint(Buf &b, uint32_t v) {
  if (v < 0x80) put(b, (uint8_t)v);                          // positive fixint
  else if (v <= 0xFF) { put(b, 0xCC); put(b, (uint8_t)v); }  // uint8
  else if (v <= 0xFFFF) { put(b, 0xCD); putBE(b, v, 2); }    // uint16
  else { put(b, 0xCE); putBE(b, v, 4); }                     // uint32
}

static void mpFloat(Buf &b, float v) {  // float32 (an AVR float is IEEE 754 single precision)
  union { float f; uint32_t u; } x;
  x.f = v;
  put(b, 0xCA);
  putBE(b, x.u, 4);
}

static void mpFloats(Buf &b, const float *v, uint8_t n) {
  mpArray(b, n);
  for (uint8_t i = 0; i < n; ++i) mpFloat(b, v[i]);
}

// ------------------------------------------------------------------------------ MessagePack reader
// Strict: any type it does not expect makes the whole message invalid (r.ok = false).

struct Rd {
  const uint8_t *p;
  uint16_t n, i;
  bool ok;
};

static uint8_t get(Rd &r) {
  if (r.i < r.n) return r.p[r.i++];
  r.ok = false;
  return 0;
}

static uint32_t getBE(Rd &r, uint8_t bytes) {
  uint32_t v = 0;
  for (uint8_t i = 0; i < bytes; ++i) v = (v << 8) | get(r);
  return v;
}

static uint8_t rdMap(Rd &r) {  // fixmap only (host bodies have <= 3 keys)
  uint8_t t = get(r);
  if ((t & 0xF0) != 0x80) r.ok = false;
  return t & 0x0F;
}

static uint8_t rdArray(Rd &r) {  // fixarray or array16
  uint8_t t = get(r);
  if ((t & 0xF0) == 0x90) return t & 0x0F;
  if (t == 0xDC) {
    uint32_t n = getBE(r, 2);
    if (n > 255) r.ok = false;
    return (uint8_t)n;
  }
  r.ok = false;
  return 0;
}

// A key (fixstr) into out (capacity cap, NUL-terminated).
static void rdKey(Rd &r, char *out, uint8_t cap) {
  uint8_t t = get(r);
  uint8_t n = t & 0x1F;
  if ((t & 0xE0) != 0xA0 || n >= cap) {
    r.ok = false;
    out[0] = 0;
    return;
  }
  for (uint8_t k = 0; k < n; ++k) out[k] = (char)get(r);
  out[n] = 0;
}

// An unsigned integer of any MessagePack width up to 32 bits (booleans are not integers).
static uint32_t rdUint(Rd &r) {
  uint8_t t = get(r);
  if (t < 0x80) return t;
  if (t == 0xCC) return getBE(r, 1);
  if (t == 0xCD) return getBE(r, 2);
  if (t == 0xCE) return getBE(r, 4);
  if (t == 0xCF) {  // uint64: only if it fits 32 bits
    if (getBE(r, 4) != 0) r.ok = false;
    return getBE(r, 4);
  }
  r.ok = false;
  return 0;
}

// Big-endian IEEE 754 double -> float (AVR has no 64-bit double): sign, exponent, top mantissa bits.
static float f64ToFloat(uint32_t hi, uint32_t lo) {
  bool neg = hi >> 31;
  int16_t e = (int16_t)((hi >> 20) & 0x7FF);
  if (e == 0x7FF) return NAN;   // inf / nan: rejected by the caller's finite check
  if (e == 0) return 0.0f;      // zero or a subnormal (|x| < 2.2e-308)
  float m = 1.0f + (float)(hi & 0xFFFFF) * 9.5367431640625e-7f  // 2^-20
            + (float)lo * 2.220446049250313e-16f;                 // 2^-52
  float v = ldexp(m, e - 1023);  // beyond float range: inf (rejected) or 0
  return neg ? -v : v;
}

// A real: float32, float64 or any integer (MessagePack); NAN if it is none of them.
static float rdFloat(Rd &r) {
  uint8_t t = r.i < r.n ? r.p[r.i] : 0;
  if (t == 0xCA) {
    r.i++;
    union { float f; uint32_t u; } x;
    x.u = getBE(r, 4);
    return x.f;
  }
  if (t == 0xCB) {
    r.i++;
    uint32_t hi = getBE(r, 4);
    uint32_t lo = getBE(r, 4);
    return f64ToFloat(hi, lo);
  }
  if (t >= 0xE0) {  // negative fixint
    r.i++;
    return (float)(int8_t)t;
  }
  if (t == 0xD0 || t == 0xD1 || t == 0xD2) {  // int8/16/32
    r.i++;
    uint8_t bytes = t == 0xD0 ? 1 : (t == 0xD1 ? 2 : 4);
    uint32_t u = getBE(r, bytes);
    int32_t v = bytes == 1 ? (int8_t)u : (bytes == 2 ? (int16_t)u : (int32_t)u);
    return (float)v;
  }
  return (float)rdUint(r);  // positive integers (sets r.ok = false for anything else)
}

// ------------------------------------------------------------------------------ frames out

// Header into raw[0..3], the body is already at raw[4..], then CRC, COBS and queue it. Returns
// false (nothing queued, seq not used) while the previous frame is still being written.
static bool queueFrame(uint8_t kind, uint16_t body_len) {
  if (tx_pos < tx_len) return false;
  raw[0] = FRAME_VERSION;
  raw[1] = kind;
  raw[2] = (uint8_t)(seq & 0xFF);  // little-endian
  raw[3] = (uint8_t)(seq >> 8);
  seq++;
  uint16_t n = 4 + body_len;
  uint16_t crc = crc16(raw, n);
  raw[n++] = (uint8_t)(crc & 0xFF);  // CRC little-endian
  raw[n++] = (uint8_t)(crc >> 8);
  tx_len = cobsEncode(raw, n, tx);
  tx[tx_len++] = 0x00;
  tx_pos = 0;
  return true;
}

// Write as much of the queued frame as the UART buffer takes now (never blocks).
static void pumpTx() {
  while (tx_pos < tx_len) {
    int room = Serial.availableForWrite();
    if (room <= 0) return;
    uint16_t k = tx_len - tx_pos;
    if ((int)k > room) k = (uint16_t)room;
    Serial.write(tx + tx_pos, k);
    tx_pos += k;
  }
}

static Buf bodyBuf() {
  Buf b = {raw + 4, 0, (uint16_t)(sizeof(raw) - 4 - 2), true};
  return b;
}

static void sendHello() {
  Buf b = bodyBuf();
  mpMap(b, 8);
  mpStr(b, "proto");        mpUint(b, PROTO_VERSION);
  mpStr(b, "model");        mpStr(b, MODEL);
  mpStr(b, "fw");           mpStr(b, FW);
  mpStr(b, "joints");       mpUint(b, JOINTS);
  mpStr(b, "lower");        mpFloats(b, LOWER, JOINTS);
  mpStr(b, "upper");        mpFloats(b, UPPER, JOINTS);
  mpStr(b, "max_velocity"); mpFloats(b, MAX_VELOCITY, JOINTS);
  mpStr(b, "rate_hz");      mpUint(b, STATE_HZ);
  hello_pending = !(b.ok && queueFrame(KIND_HELLO, b.n));  // retried while the UART is busy
}

static void sendState(uint32_t t_us) {
  static const float zero[MAX_J] = {0};
  Buf b = bodyBuf();
  mpMap(b, 8);
  mpStr(b, "t_us");             mpUint(b, t_us);
  mpStr(b, "q");                mpFloats(b, q_meas, JOINTS);
  mpStr(b, "qd");               mpFloats(b, qd_meas, JOINTS);
  mpStr(b, "current");          mpFloats(b, zero, JOINTS);
  mpStr(b, "fault");            mpUint(b, faults);
  mpStr(b, "last_seq_applied"); mpUint(b, last_seq_applied);
  mpStr(b, "watchdog_tripped"); mpBool(b, tripped);
  mpStr(b, "enabled");          mpBool(b, enabled);
  if (b.ok) queueFrame(KIND_STATE, b.n);  // skipped (not queued, no seq used) if the UART is busy
}

// ------------------------------------------------------------------------------ servos

static int16_t pulseOf(uint8_t j, float q) {
  float us = CENTER_US[j] + US_PER_RAD[j] * q;
  if (us < MIN_US[j]) us = MIN_US[j];
  if (us > MAX_US[j]) us = MAX_US[j];
  return (int16_t)(us + 0.5f);
}

static void attachServos() {
  if (attached) return;
  for (uint8_t j = 0; j < JOINTS; ++j) {
    servo[j].writeMicroseconds(pulseOf(j, q_cmd[j]));  // the first pulse is where the joint is
    servo[j].attach(SERVO_PIN[j]);                      // (Servo keeps the value written before)
  }
  attached = true;
}

static void releaseServos() {
  if (!attached) return;
  for (uint8_t j = 0; j < JOINTS; ++j) servo[j].detach();
  attached = false;
}

// Stop where the joints are: targets = the commanded positions; optionally limp.
static void hold() {
  for (uint8_t j = 0; j < JOINTS; ++j) target[j] = q_cmd[j];
  wd_armed = false;
  if (RELEASE_ON_HOLD) releaseServos();
}

static void raiseFault(uint8_t bits) {
  faults |= bits;
  enabled = false;
  hold();
  if (bits & FAULT_ESTOP) releaseServos();  // the e-stop cuts servo power in hardware too
}

// Move each commanded position toward its target no faster than MAX_VELOCITY; write the pulses.
static void moveServos(float dt) {
  for (uint8_t j = 0; j < JOINTS; ++j) {
    float step = target[j] - q_cmd[j];
    float lim = MAX_VELOCITY[j] * dt;
    if (step > lim) step = lim;
    if (step < -lim) step = -lim;
    q_cmd[j] += step;
    if (attached) servo[j].writeMicroseconds(pulseOf(j, q_cmd[j]));
  }
}

// Measure (feedback pins) or take the commanded position, as the servo can reach it.
static void measure(uint32_t now_us, uint32_t now_ms) {
  float dt = (now_us - last_meas_us) * 1e-6f;
  last_meas_us = now_us;
  for (uint8_t j = 0; j < JOINTS; ++j) {
    float q;
    if (FB_PIN[j] >= 0) {
      q = (analogRead(FB_PIN[j]) - FB_ZERO[j]) * FB_RAD_PER_COUNT[j];
      if (enabled && fabs(q - q_cmd[j]) > FOLLOW_ERROR_RAD) {
        if (follow_bad_since[j] == 0) follow_bad_since[j] = now_ms | 1;
        else if (now_ms - follow_bad_since[j] > FOLLOW_ERROR_MS) raiseFault(FAULT_FOLLOWING);
      } else {
        follow_bad_since[j] = 0;
      }
    } else {
      q = (pulseOf(j, q_cmd[j]) - CENTER_US[j]) / US_PER_RAD[j];  // clipped to the servo's travel
    }
    qd_meas[j] = dt > 0 ? (q - q_meas[j]) / dt : 0.0f;
    q_meas[j] = q;
  }
}

// ------------------------------------------------------------------------------ host messages

static bool keyIs(const char *k, const char *want) { return strcmp(k, want) == 0; }

static uint8_t presentFaults() {  // fault causes that are still there (ENABLE keeps these)
  return digitalRead(PIN_ESTOP) == HIGH ? FAULT_ESTOP : 0;
}

static void onEnable(uint32_t s) {
  faults &= presentFaults();
  tripped = false;
  for (uint8_t j = 0; j < JOINTS; ++j) {
    if (FB_PIN[j] >= 0) q_cmd[j] = q_meas[j];  // start from where the joint really is
    target[j] = q_cmd[j];
  }
  wd_armed = false;
  last_seq_applied = s;
  enabled = faults == 0;
  if (enabled) attachServos();
}

static void onSetpoint(uint32_t s, const float *q, uint8_t n, uint32_t timeout_ms) {
  if (!enabled) return;                                  // ignored while disabled or tripped
  if ((int32_t)(s - last_seq_applied) <= 0) return;     // a duplicate or a late SETPOINT (mod 2^32)
  bool ok = n == JOINTS && timeout_ms >= 1 && timeout_ms <= MAX_TIMEOUT_MS;
  for (uint8_t j = 0; ok && j < JOINTS; ++j) ok = isfinite(q[j]) && q[j] >= LOWER[j] && q[j] <= UPPER[j];
  if (!ok) {
    raiseFault(FAULT_SETPOINT);
    return;
  }
  for (uint8_t j = 0; j < JOINTS; ++j) target[j] = q[j];
  last_seq_applied = s;
  wd_armed = true;
  wd_last_ms = millis();
  wd_timeout_ms = timeout_ms;
}

// A complete incoming frame (without its 0x00): check it, parse the body strictly, act.
static void handleFrame(const uint8_t *in, uint16_t n) {
  static uint8_t dec[256];
  int16_t m = cobsDecode(in, n, dec, sizeof(dec));
  if (m < 4 + 1 + 2) return;  // header + at least one body byte + CRC
  uint16_t got = (uint16_t)dec[m - 2] | ((uint16_t)dec[m - 1] << 8);
  if (crc16(dec, (uint16_t)(m - 2)) != got) return;
  if (dec[0] != FRAME_VERSION) return;
  uint8_t kind = dec[1];
  Rd r = {dec + 4, (uint16_t)(m - 4 - 2), 0, true};
  uint8_t keys = rdMap(r);
  char key[16];
  if (kind == KIND_HELLO_REQUEST) {  // {"proto": 1}
    uint32_t proto = 0;
    for (uint8_t k = 0; k < keys && r.ok; ++k) {
      rdKey(r, key, sizeof(key));
      if (keyIs(key, "proto")) proto = rdUint(r);
      else r.ok = false;
    }
    if (r.ok && keys == 1 && r.i == r.n && proto == PROTO_VERSION) sendHello();
  } else if (kind == KIND_ENABLE) {  // {"seq": s}
    uint32_t s = 0;
    for (uint8_t k = 0; k < keys && r.ok; ++k) {
      rdKey(r, key, sizeof(key));
      if (keyIs(key, "seq")) s = rdUint(r);
      else r.ok = false;
    }
    if (r.ok && keys == 1 && r.i == r.n) onEnable(s);
  } else if (kind == KIND_DISABLE) {  // {}
    if (r.ok && keys == 0 && r.i == r.n) {
      enabled = false;
      hold();
    }
  } else if (kind == KIND_SETPOINT) {  // {"seq": s, "q": [...], "timeout_ms": t}
    uint32_t s = 0, timeout_ms = 0;
    float q[MAX_J];
    uint8_t nq = 0, seen = 0;
    for (uint8_t k = 0; k < keys && r.ok; ++k) {
      rdKey(r, key, sizeof(key));
      if (keyIs(key, "seq")) { s = rdUint(r); seen |= 1; }
      else if (keyIs(key, "timeout_ms")) { timeout_ms = rdUint(r); seen |= 2; }
      else if (keyIs(key, "q")) {
        nq = rdArray(r);
        for (uint8_t j = 0; j < nq && r.ok; ++j) {
          float v = rdFloat(r);
          if (j < MAX_J) q[j] = v;
        }
        seen |= 4;
      } else r.ok = false;
    }
    if (r.ok && keys == 3 && seen == 7 && r.i == r.n) onSetpoint(s, q, nq > MAX_J ? MAX_J + 1 : nq, timeout_ms);
  }
  // anything else (a malformed body, an unknown kind) is ignored: the host's own timers notice
}

static void pollSerial() {
  while (Serial.available() > 0) {
    uint8_t c = (uint8_t)Serial.read();
    if (c == 0x00) {  // frame end (two in a row: idle fill)
      if (!rx_overflow && rx_len > 0) handleFrame(rx, rx_len);
      rx_len = 0;
      rx_overflow = false;
    } else if (rx_len < sizeof(rx)) {
      rx[rx_len++] = c;
    } else {
      rx_overflow = true;  // too long: drop it, resynchronise on the next 0x00
    }
  }
}

// ------------------------------------------------------------------------------ Arduino

void setup() {
  pinMode(PIN_ESTOP, INPUT_PULLUP);
  for (uint8_t j = 0; j < JOINTS; ++j) {
    q_cmd[j] = target[j] = q_meas[j] = HOME[j];
    qd_meas[j] = 0.0f;
    follow_bad_since[j] = 0;
  }
  Serial.begin(BAUD);
  uint8_t zero = 0x00;
  Serial.write(&zero, 1);  // ends any half frame the host may have buffered
  last_move_us = last_meas_us = micros();
  measure(last_meas_us, millis());
  sendHello();             // boot HELLO; a host that opens the port later sends HELLO_REQUEST
  next_state_us = micros();
}

void loop() {
  pollSerial();
  uint32_t now_us = micros();
  uint32_t now_ms = millis();
  if (presentFaults() & ~faults) raiseFault(presentFaults());
  if (enabled && wd_armed && now_ms - wd_last_ms > wd_timeout_ms) {  // the controller's watchdog
    tripped = true;
    enabled = false;
    hold();
  }
  float dt = (now_us - last_move_us) * 1e-6f;
  last_move_us = now_us;
  moveServos(dt);
  if ((int32_t)(now_us - next_state_us) >= 0) {  // wrap-safe "deadline reached"
    next_state_us += 1000000UL / STATE_HZ;
    if ((int32_t)(now_us - next_state_us) >= 0) next_state_us = now_us + 1000000UL / STATE_HZ;  // fell behind
    measure(now_us, now_ms);
    if (hello_pending) sendHello();
    else sendState(now_us);
  }
  pumpTx();
}
