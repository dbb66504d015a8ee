// dioptra serial-line photodiode: the device side of line protocol version 1
// (firmware-protocol/photodiode/README.md).
//
// A comparator's digital output (a photodiode and an LM393, or a light-sensor module's DO pin)
// on an interrupt-capable pin. Every change of it is timestamped inside the interrupt with a
// 64-bit microsecond clock, queued, and written from loop() as "<t_us>,<level>\n" (level 1:
// the light came on). "v\n" asks for the hello line, "s\n" for the clock ("s,<t_us>\n").
//
// Not compiled in dioptra's CI (no AVR/ARM toolchain there). Build with the Arduino IDE or
// arduino-cli for any Arduino-compatible board (Uno, Nano, Leonardo, Teensy, Pico, SAMD).

#include <Arduino.h>

// The comparator's output. Uno/Nano: pin 2 or 3; boards with interrupts on every pin: any.
const uint8_t SENSOR_PIN = 2;
// Many LM393 light-sensor modules pull DO low while the light is above their threshold.
const bool ACTIVE_LOW = true;
// What the hello line says about this build (at most 40 bytes).
const char ABOUT[] = "arduino sketch 1.0";
const unsigned long BAUD = 115200;

// Edges waiting to be written. A power of two, so the indices wrap with a mask.
const uint8_t QUEUE = 64;
volatile uint32_t edgeLow[QUEUE];   // the 64-bit time, split: AVR has no atomic 64-bit store
volatile uint32_t edgeHigh[QUEUE];
volatile uint8_t edgeLevel[QUEUE];
volatile uint8_t head = 0;  // written by the interrupt
volatile uint8_t tail = 0;  // written by loop()
volatile uint32_t dropped = 0;

// micros() wraps every 71.6 minutes; this counts the wraps. Call with interrupts off, at least
// once per wrap (loop() does, every pass).
volatile uint32_t clockHigh = 0;
volatile uint32_t clockLast = 0;

uint64_t micros64() {
  uint32_t now = micros();
  if (now < clockLast) {
    clockHigh++;
  }
  clockLast = now;
  return ((uint64_t)clockHigh << 32) | now;
}

void onEdge() {
  // Interrupts are off inside an interrupt handler.
  uint64_t t = micros64();
  uint8_t level = (digitalRead(SENSOR_PIN) == HIGH) != ACTIVE_LOW ? 1 : 0;
  uint8_t next = (head + 1) & (QUEUE - 1);
  if (next == tail) {
    dropped++;  // full: reported as "!overflow,<n>"
    return;
  }
  edgeLow[head] = (uint32_t)t;
  edgeHigh[head] = (uint32_t)(t >> 32);
  edgeLevel[head] = level;
  head = next;
}

// Arduino's Print has no 64-bit numbers on AVR.
void printU64(uint64_t v) {
  char digits[21];
  uint8_t n = 0;
  do {
    digits[n++] = '0' + (char)(v % 10);
    v /= 10;
  } while (v > 0);
  while (n > 0) {
    Serial.write(digits[--n]);
  }
}

void hello() {
  Serial.print("dioptra-photodiode,1,");
  Serial.print(ABOUT);
  Serial.write('\n');
}

char command[16];
uint8_t commandLen = 0;
uint64_t commandTime = 0;  // when the command's first byte was read

void runCommand() {
  if (commandLen == 0) {
    return;
  }
  if (commandLen == 1 && command[0] == 'v') {
    hello();
  } else if (commandLen == 1 && command[0] == 's') {
    Serial.print("s,");
    printU64(commandTime);
    Serial.write('\n');
  } else {
    Serial.print("#unknown command\n");
  }
}

void setup() {
  pinMode(SENSOR_PIN, INPUT);
  Serial.begin(BAUD);
  // Native-USB boards: wait (briefly) for the host to open the port, so the hello is seen.
  unsigned long start = millis();
  while (!Serial && millis() - start < 2000) {
  }
  attachInterrupt(digitalPinToInterrupt(SENSOR_PIN), onEdge, CHANGE);
  hello();
}

void loop() {
  // Keeps the 64-bit clock's wrap count current when no edge comes for a long time.
  noInterrupts();
  micros64();
  interrupts();

  while (Serial.available() > 0) {
    int c = Serial.read();
    if (c == '\r') {
      continue;
    }
    if (c == '\n') {
      runCommand();
      commandLen = 0;
    } else if (commandLen < sizeof(command)) {
      if (commandLen == 0) {
        // The clock when the command was read: as close to its arrival as a loop gets.
        noInterrupts();
        commandTime = micros64();
        interrupts();
      }
      command[commandLen++] = (char)c;
    }
  }

  // Edges queued before the queue filled come before the ones it dropped: write those, then
  // the overflow. What the interrupt queues meanwhile waits for the next pass.
  noInterrupts();
  uint8_t end = head;
  uint32_t lost = dropped;
  dropped = 0;
  interrupts();
  while (tail != end) {
    noInterrupts();
    uint64_t t = ((uint64_t)edgeHigh[tail] << 32) | edgeLow[tail];
    uint8_t level = edgeLevel[tail];
    interrupts();
    printU64(t);
    Serial.write(',');
    Serial.write(level ? '1' : '0');
    Serial.write('\n');
    tail = (tail + 1) & (QUEUE - 1);
  }
  if (lost > 0) {
    Serial.print("!overflow,");
    Serial.print(lost);
    Serial.write('\n');
  }
}
