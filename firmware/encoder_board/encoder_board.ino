/*
 * encoder_board.ino — reference firmware of the all-joints master's encoder board (telesurg).
 *
 * Reads the sensors of the ergonomic all-joints master (Shim 2015, Table 3 / Section 2.3):
 *   joint 1  shoulder slide   on/off switch             -> "sw" bit0
 *   joint 2  elbow yaw        quadrature encoder (400)  -> "counts"[0]
 *   joint 3  wrist yaw        quadrature encoder (400)  -> "counts"[1]
 *   joint 4  wrist pitch      quadrature encoder (400)  -> "counts"[2]
 *   joint 5  wrist roll       quadrature encoder (400)  -> "counts"[3]
 *   joint 6  finger slide     linear potentiometer      -> "pot" (10-bit ADC)
 *   clutch pedal, operator-present sensor               -> "sw" bit1, bit2
 * and streams them to the host in telesurg's serial frames. The protocol is specified byte by
 * byte in shared/encoder_protocol.py (module docstring) and docs/hardware.md; in short:
 *
 *   wire   = COBS(raw) 0x00
 *   raw    = version(1) kind(u8) seq(u16 LE) body(MessagePack map) CRC-16/CCITT-FALSE(u16 LE)
 *   kinds  0x01 HELLO   {"proto","model","fw","joints","encoders","counts_per_rev","rate_hz"}
 *          0x02 SAMPLE  {"t_us","counts","pot","sw"}
 *          0x10 HELLO_REQUEST (host -> board): answered with a HELLO
 *
 * HELLO goes out at boot, every HELLO_PERIOD_MS and on request, so a host that opens the port at
 * any time (and boards that do not reset on open, e.g. native USB) learn the layout quickly.
 *
 * Board: Arduino Mega 2560 (5 V, interrupt pins 2, 3, 18, 19, 20, 21). Library: "Encoder" by
 * Paul Stoffregen (Arduino Library Manager). Not compiled in CI; keep it in step with
 * shared/encoder_protocol.py when the protocol changes (PROTO_VERSION).
 *
 * Link budget: a SAMPLE is at most 58 bytes on the wire; at 115200 bit/s (11 520 bytes/s) that
 * allows ~198 SAMPLEs/s, so SAMPLE_HZ = 100 uses half the link. For 500 Hz set BAUD 500000
 * (exact on a 16 MHz AVR) and tell the host: --set serial.baud=500000.
 */

#include <Encoder.h>
#include <string.h>

// ------------------------------------------------------------------------------ configuration

static const uint32_t BAUD = 115200;          // bit/s; host: serial.baud
static const uint16_t SAMPLE_HZ = 100;        // SAMPLE rate, Hz (see the link budget above)
static const uint16_t HELLO_PERIOD_MS = 1000; // periodic HELLO, ms
static const uint16_t DEBOUNCE_MS = 5;        // a switch must be stable this long, ms
// Counts per revolution as the Encoder library counts them: every edge of A and B, i.e. 4 x the
// encoder's lines (100 lines -> 400, 400 lines -> 1600). Measure it (docs/hardware.md, calibration
// step 3); the host's serial.calibration.counts_per_rev must be the same (else the HELLO is refused).
static const uint16_t COUNTS_PER_REV = 400;
static const char MODEL[] = "plas-master";
static const char FW[] = "0.1.0";
static const uint8_t JOINTS = 6;
static const uint8_t N_ENC = 4;               // encoders on joints 2..5 (host: calibration.encoder_joints)

static const uint8_t FRAME_VERSION = 1;
static const uint8_t PROTO_VERSION = 1;
static const uint8_t KIND_HELLO = 0x01;
static const uint8_t KIND_SAMPLE = 0x02;
static const uint8_t KIND_HELLO_REQUEST = 0x10;

// ------------------------------------------------------------------------------ pins (Mega 2560)
// Encoders: A/B. Both pins on interrupts for joints 2 and 3 (best), the A pin only for joints 4
// and 5 (the library's "good performance" mode: every edge still counted at hand speeds).
// Pins 20/21 also carry the Mega's on-board 10 k I2C pull-ups: harmless for encoder outputs.
Encoder enc2(2, 3);    // joint 2 elbow yaw
Encoder enc3(18, 19);  // joint 3 wrist yaw
Encoder enc4(20, 22);  // joint 4 wrist pitch
Encoder enc5(21, 23);  // joint 5 wrist roll
Encoder *const ENC[N_ENC] = {&enc2, &enc3, &enc4, &enc5};

static const uint8_t PIN_POT = A0;       // joint 6 finger-slide potentiometer wiper (ends: 5 V, GND)
static const uint8_t PIN_JOINT1 = 30;    // joint-1 switch to GND (pressed = LOW)
static const uint8_t PIN_CLUTCH = 31;    // clutch pedal to GND (pressed = LOW)
static const uint8_t PIN_OPERATOR = 32;  // operator-present sensor, active LOW
// Active-low inputs with pull-ups fail safe: a broken wire reads "released" / "absent".

// ------------------------------------------------------------------------------ state

static uint16_t seq = 0;               // one counter for every frame this board writes
static uint32_t next_sample_us = 0;
static uint32_t last_hello_ms = 0;
static uint8_t sw_candidate = 0, sw_stable = 0;
static uint32_t sw_since_ms = 0;

static uint8_t rx[64];                 // one incoming COBS frame (HELLO_REQUEST is 11 bytes)
static uint8_t rx_len = 0;
static bool rx_overflow = false;

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

// COBS-encode n bytes (n < 254 here) into out (n + 1 bytes); returns the encoded length.
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

// ------------------------------------------------------------------------------ tiny MessagePack writer
// Only what the two bodies need, always the smallest encoding (the same bytes as Python's
// msgpack.packb): fixmap, fixarray, fixstr, and integers. MessagePack integers are big-endian.

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

static void mpStr(Buf &b, const char *s) {  // fixstr: up to 31 bytes
  uint8_t n = (uint8_t)strlen(s);
  put(b, 0xA0 | n);
  for (uint8_t i = 0; i < n; ++i) put(b, (uint8_t)s[i]);
}

static void mpUint(Buf &b, uint32_t v) {
  if (v < 0x80) put(b, (uint8_t)v);                        // positive fixint
  else if (v <= 0xFF) { put(b, 0xCC); put(b, (uint8_t)v); }  // uint8
  else if (v <= 0xFFFF) { put(b, 0xCD); putBE(b, v, 2); }  // uint16
  else { put(b, 0xCE); putBE(b, v, 4); }                   // uint32
}

static void mpInt(Buf &b, int32_t v) {
  if (v >= 0) mpUint(b, (uint32_t)v);
  else if (v >= -32) put(b, (uint8_t)(int8_t)v);                                // negative fixint
  else if (v >= -128) { put(b, 0xD0); put(b, (uint8_t)(int8_t)v); }             // int8
  else if (v >= -32768) { put(b, 0xD1); putBE(b, (uint16_t)(int16_t)v, 2); }    // int16
  else { put(b, 0xD2); putBE(b, (uint32_t)v, 4); }                              // int32
}

// ------------------------------------------------------------------------------ frames

static uint8_t raw[128];
static uint8_t wire[132];

// Header into raw[0..3], body written by the caller from raw[4], then CRC, COBS and send.
// A SAMPLE that does not fit in the UART transmit buffer is skipped rather than blocking the loop;
// its seq is still used up, so the host counts it as lost (a gap). HELLOs always go out.
static void sendFrame(uint8_t kind, uint16_t body_len, bool may_skip) {
  raw[0] = FRAME_VERSION;
  raw[1] = kind;
  raw[2] = (uint8_t)(seq & 0xFF);
  raw[3] = (uint8_t)(seq >> 8);
  seq++;
  uint16_t n = 4 + body_len;
  uint16_t crc = crc16(raw, n);
  raw[n++] = (uint8_t)(crc & 0xFF);  // CRC little-endian
  raw[n++] = (uint8_t)(crc >> 8);
  uint16_t len = cobsEncode(raw, n, wire);
  wire[len++] = 0x00;
  if (may_skip && Serial.availableForWrite() < (int)len) return;
  Serial.write(wire, len);
}

static Buf bodyBuf() {
  Buf b = {raw + 4, 0, (uint16_t)(sizeof(raw) - 4 - 2), true};
  return b;
}

static void sendHello() {
  Buf b = bodyBuf();
  mpMap(b, 7);
  mpStr(b, "proto");          mpUint(b, PROTO_VERSION);
  mpStr(b, "model");          mpStr(b, MODEL);
  mpStr(b, "fw");             mpStr(b, FW);
  mpStr(b, "joints");         mpUint(b, JOINTS);
  mpStr(b, "encoders");       mpUint(b, N_ENC);
  mpStr(b, "counts_per_rev"); mpUint(b, COUNTS_PER_REV);
  mpStr(b, "rate_hz");        mpUint(b, SAMPLE_HZ);
  if (b.ok) sendFrame(KIND_HELLO, b.n, false);
}

static uint16_t readPot() {  // 4 readings averaged, still 0..1023
  uint16_t sum = 0;
  for (uint8_t i = 0; i < 4; ++i) sum += analogRead(PIN_POT);
  return (sum + 2) >> 2;
}

static uint8_t readSwitchesRaw() {  // bit0 joint 1, bit1 clutch, bit2 operator present
  return (digitalRead(PIN_JOINT1) == LOW ? 0x01 : 0) | (digitalRead(PIN_CLUTCH) == LOW ? 0x02 : 0) |
         (digitalRead(PIN_OPERATOR) == LOW ? 0x04 : 0);
}

static void debounceSwitches(uint32_t now_ms) {
  uint8_t s = readSwitchesRaw();
  if (s != sw_candidate) {
    sw_candidate = s;
    sw_since_ms = now_ms;
  } else if (now_ms - sw_since_ms >= DEBOUNCE_MS) {
    sw_stable = s;
  }
}

static void sendSample(uint32_t t_us) {
  int32_t counts[N_ENC];
  for (uint8_t k = 0; k < N_ENC; ++k) counts[k] = ENC[k]->read();
  uint16_t pot = readPot();
  Buf b = bodyBuf();
  mpMap(b, 4);
  mpStr(b, "t_us");   mpUint(b, t_us);
  mpStr(b, "counts"); mpArray(b, N_ENC);
  for (uint8_t k = 0; k < N_ENC; ++k) mpInt(b, counts[k]);
  mpStr(b, "pot");    mpUint(b, pot);
  mpStr(b, "sw");     mpUint(b, sw_stable);
  if (b.ok) sendFrame(KIND_SAMPLE, b.n, true);
}

// A complete incoming frame (without its 0x00): answer a valid HELLO_REQUEST with a HELLO.
// The body ({"proto": 1}) is not parsed: the kind is enough for this board.
static void handleFrame(const uint8_t *in, uint8_t n) {
  static uint8_t dec[64];
  int16_t m = cobsDecode(in, n, dec, sizeof(dec));
  if (m < 4 + 1 + 2) return;  // header + at least one body byte + CRC
  uint16_t got = (uint16_t)dec[m - 2] | ((uint16_t)dec[m - 1] << 8);
  if (crc16(dec, (uint16_t)(m - 2)) != got) return;
  if (dec[0] != FRAME_VERSION) return;
  if (dec[1] == KIND_HELLO_REQUEST) sendHello();
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
      rx_overflow = true;  // too long for a host frame: drop it, resynchronise on the next 0x00
    }
  }
}

// ------------------------------------------------------------------------------ Arduino

void setup() {
  pinMode(PIN_JOINT1, INPUT_PULLUP);
  pinMode(PIN_CLUTCH, INPUT_PULLUP);
  pinMode(PIN_OPERATOR, INPUT_PULLUP);
  // The Encoder constructors already enabled the pull-ups on the encoder pins.
  Serial.begin(BAUD);
  uint8_t zero = 0x00;
  Serial.write(&zero, 1);  // ends any half frame the host may have buffered
  sw_candidate = sw_stable = readSwitchesRaw();
  sw_since_ms = millis();
  sendHello();
  last_hello_ms = millis();
  next_sample_us = micros();
}

void loop() {
  pollSerial();
  uint32_t now_ms = millis();
  debounceSwitches(now_ms);
  uint32_t now_us = micros();
  if ((int32_t)(now_us - next_sample_us) >= 0) {  // wrap-safe "deadline reached"
    next_sample_us += 1000000UL / SAMPLE_HZ;
    if ((int32_t)(now_us - next_sample_us) >= 0) next_sample_us = now_us + 1000000UL / SAMPLE_HZ;  // fell behind
    sendSample(now_us);
  }
  if (now_ms - last_hello_ms >= HELLO_PERIOD_MS) {
    last_hello_ms = now_ms;
    sendHello();
  }
}
