// Just enough of the Arduino API to run firmware-protocol/photodiode's sketch on a Linux host,
// for crates/photodiode/tests/sketch.rs: Serial is a pty (raw), micros() a 32-bit counter that
// starts 0.3 s before it wraps, and the sensor pin is driven by main.cpp's schedule.
#pragma once
#include <stdint.h>
#include <stddef.h>

#define HIGH 1
#define LOW 0
#define INPUT 0
#define CHANGE 1
#define digitalPinToInterrupt(p) (p)

uint32_t micros();
unsigned long millis();
int digitalRead(uint8_t pin);
void pinMode(uint8_t pin, uint8_t mode);
void attachInterrupt(uint8_t interrupt, void (*isr)(), int mode);
void noInterrupts();
void interrupts();

class HostSerial {
 public:
  void begin(unsigned long baud);
  explicit operator bool() const { return true; }
  int available();
  int read();
  size_t write(char c);
  size_t print(const char* s);
  size_t print(unsigned long v);
};

extern HostSerial Serial;
