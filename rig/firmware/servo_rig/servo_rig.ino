// servo_rig: the tapping rig's two hobby servos on an Arduino Mega (ATmega2560).
//
// Speaks the line protocol documented in rig/servo_protocol.py (the one home of the
// protocol; rig/twins/servos.py mirrors this sketch and tests/test_rig_servos.py checks
// that the constants below agree with the Python ones):
//   host:  H | S <id> <deg> | ? <id> | C <id> <offset_deg>      framed  <body>*<xor>
//   board: OK <echo> | ERR <code> <message> | READY servo_rig <v>  framed the same way
// Ids: R = sensor roll, P = indenter pitch. Angles are degrees with two decimals, held as
// integer centidegrees (no float parsing). Nothing is clamped: out of range is ERR.
// A servo is attached only on its first S, so nothing moves at boot.

#include <Servo.h>

#define FIRMWARE "servo_rig"
#define PROTOCOL_VERSION 1
#define BAUD 115200L
#define MAX_LINE_BYTES 31

// Servo pins (any digital pin works with the Servo library).
const uint8_t ROLL_PIN = 9;
const uint8_t PITCH_PIN = 10;

// Travel, centidegrees: scenes/kinematics.py's ROLL_TRAVEL_RAD and PITCH_TRAVEL_RAD, rounded inwards.
const long ROLL_MIN_CD = -1145;
const long ROLL_MAX_CD = 19145;
const long PITCH_MIN_CD = -2005;
const long PITCH_MAX_CD = 11005;
// Calibration offsets at boot, centidegrees: horn angle = angle + offset. Measure on the rig.
const long ROLL_OFFSET_CD = 0;
const long PITCH_OFFSET_CD = 0;
const long MAX_OFFSET_CD = 2000;
// Horn angles the Servo library maps to pulses, and those pulses (Servo.h's defaults).
const long HORN_MIN_CD = 0;
const long HORN_MAX_CD = 18000;
const long PULSE_MIN_US = 544;
const long PULSE_MAX_US = 2400;

// Error codes (rig.servo_protocol.Code).
enum { E_CHECKSUM = 1, E_OVERFLOW = 2, E_SYNTAX = 3, E_SERVO = 4, E_TRAVEL = 5, E_PULSE = 6,
       E_OFFSET = 7, E_UNSET = 8 };

struct Joint {
  char id;
  uint8_t pin;
  long min_cd, max_cd;  // travel
  long offset_cd;       // calibration offset
  long angle_cd;        // last angle set
  bool set;             // angle_cd is valid and the servo is attached
  Servo servo;
};

Joint joints[2] = {
  {'R', ROLL_PIN, ROLL_MIN_CD, ROLL_MAX_CD, ROLL_OFFSET_CD, 0, false, Servo()},
  {'P', PITCH_PIN, PITCH_MIN_CD, PITCH_MAX_CD, PITCH_OFFSET_CD, 0, false, Servo()},
};

char line[MAX_LINE_BYTES + 1];  // the line being received
uint8_t line_len = 0;
bool overflow = false;          // the current line outgrew `line`
char reply[64];

uint8_t xor_of(const char *s) {
  uint8_t x = 0;
  while (*s) x ^= (uint8_t)*s++;
  return x;
}

// Write `body*checksum\n`.
void say(const char *body) {
  Serial.print(body);
  Serial.print('*');
  Serial.println(xor_of(body));
}

void say_err(int code, const char *message) {
  snprintf(reply, sizeof reply, "ERR %d %s", code, message);
  say(reply);
}

// Centidegrees as "-11.45".
void format_cd(long cd, char *out, size_t n) {
  unsigned long a = cd < 0 ? -cd : cd;
  snprintf(out, n, "%s%lu.%02lu", cd < 0 ? "-" : "", a / 100, a % 100);
}

// "-11.45", "90", "90.5" -> centidegrees; false if malformed (same grammar as parse_centideg).
bool parse_cd(const char *s, long *out) {
  bool negative = false;
  if (*s == '-') { negative = true; s++; }
  long whole = 0;
  uint8_t digits = 0;
  while (*s >= '0' && *s <= '9') {
    if (++digits > 5) return false;
    whole = whole * 10 + (*s++ - '0');
  }
  if (digits == 0) return false;
  long frac = 0;
  if (*s == '.') {
    s++;
    uint8_t fd = 0;
    while (*s >= '0' && *s <= '9') {
      if (++fd > 2) return false;
      frac = frac * 10 + (*s++ - '0');
    }
    if (fd == 0) return false;
    if (fd == 1) frac *= 10;
  }
  if (*s != '\0') return false;
  *out = negative ? -(whole * 100 + frac) : whole * 100 + frac;
  return true;
}

Joint *joint(const char *id) {
  if (id[0] == '\0' || id[1] != '\0') return NULL;
  for (uint8_t i = 0; i < 2; i++)
    if (joints[i].id == id[0]) return &joints[i];
  return NULL;
}

long pulse_us(long horn_cd) {
  long span = HORN_MAX_CD - HORN_MIN_CD;
  return PULSE_MIN_US + ((horn_cd - HORN_MIN_CD) * (PULSE_MAX_US - PULSE_MIN_US) + span / 2) / span;
}

// Run one command whose checksum holds; `body` is modified (split into words).
void execute(char *body) {
  char *words[4];
  uint8_t n = 0;
  for (char *w = strtok(body, " "); w != NULL; w = strtok(NULL, " ")) {
    if (n == 4) { say_err(E_SYNTAX, "bad command"); return; }
    words[n++] = w;
  }
  if (n == 0) { say_err(E_SYNTAX, "bad command"); return; }
  char letter = words[0][1] == '\0' ? words[0][0] : 0;
  char a[12], b[12];
  if (letter == 'H' && n == 1) {
    snprintf(reply, sizeof reply, "OK H %s %d", FIRMWARE, PROTOCOL_VERSION);
    say(reply);
    return;
  }
  if (!(letter == 'S' || letter == '?' || letter == 'C') || n != (letter == '?' ? 2 : 3)) {
    say_err(E_SYNTAX, "bad command");
    return;
  }
  Joint *j = joint(words[1]);
  if (j == NULL) {
    snprintf(reply, sizeof reply, "no servo %s", words[1]);
    say_err(E_SERVO, reply);
    return;
  }
  if (letter == '?') {
    if (!j->set) {
      snprintf(reply, sizeof reply, "ERR %d %c not set", E_UNSET, j->id);
      say(reply);
      return;
    }
    format_cd(j->angle_cd, a, sizeof a);
    snprintf(reply, sizeof reply, "OK ? %c %s", j->id, a);
    say(reply);
    return;
  }
  long value;
  if (!parse_cd(words[2], &value)) { say_err(E_SYNTAX, "bad number"); return; }
  if (letter == 'C') {
    if (value > MAX_OFFSET_CD || value < -MAX_OFFSET_CD) {
      format_cd(MAX_OFFSET_CD, a, sizeof a);
      snprintf(reply, sizeof reply, "ERR %d %c offset beyond %s", E_OFFSET, j->id, a);
      say(reply);
      return;
    }
    j->offset_cd = value;  // applies from the next S
    format_cd(value, a, sizeof a);
    snprintf(reply, sizeof reply, "OK C %c %s", j->id, a);
    say(reply);
    return;
  }
  if (value < j->min_cd || value > j->max_cd) {
    format_cd(j->min_cd, a, sizeof a);
    format_cd(j->max_cd, b, sizeof b);
    snprintf(reply, sizeof reply, "ERR %d %c outside %s..%s", E_TRAVEL, j->id, a, b);
    say(reply);
    return;
  }
  long horn = value + j->offset_cd;
  if (horn < HORN_MIN_CD || horn > HORN_MAX_CD) {
    format_cd(horn, a, sizeof a);
    snprintf(reply, sizeof reply, "ERR %d %c horn %s outside pulse range", E_PULSE, j->id, a);
    say(reply);
    return;
  }
  if (!j->set) j->servo.attach(j->pin, PULSE_MIN_US, PULSE_MAX_US);
  j->servo.writeMicroseconds(pulse_us(horn));
  j->angle_cd = value;
  j->set = true;
  format_cd(value, a, sizeof a);
  snprintf(reply, sizeof reply, "OK S %c %s", j->id, a);
  say(reply);
}

void handle_line() {
  if (overflow) {
    snprintf(reply, sizeof reply, "line longer than %d bytes", MAX_LINE_BYTES);
    say_err(E_OVERFLOW, reply);
    return;
  }
  char *star = strrchr(line, '*');
  bool good = star != NULL && star[1] != '\0';
  unsigned int sum = 0;
  for (char *p = good ? star + 1 : NULL; good && *p; p++) {
    if (*p < '0' || *p > '9' || sum > 255) { good = false; break; }
    sum = sum * 10 + (*p - '0');
  }
  if (good) {
    *star = '\0';
    good = sum == xor_of(line);
  }
  if (!good) { say_err(E_CHECKSUM, "bad checksum"); return; }
  execute(line);
}

void setup() {
  Serial.begin(BAUD);
  snprintf(reply, sizeof reply, "READY %s %d", FIRMWARE, PROTOCOL_VERSION);
  say(reply);
}

void loop() {
  while (Serial.available() > 0) {
    char c = Serial.read();
    if (c == '\n' || c == '\r') {
      if (line_len > 0 || overflow) {
        line[line_len] = '\0';
        handle_line();
      }
      line_len = 0;
      overflow = false;
    } else if (line_len < MAX_LINE_BYTES) {
      line[line_len++] = c;
    } else {
      overflow = true;
    }
  }
}
