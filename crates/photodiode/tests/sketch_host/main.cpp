// Runs the sketch (setup(), then loop() for ever) on a pty given as argv[1], with the sensor
// pin toggled on a fixed schedule. Every time the sketch's interrupt handler runs, the 64-bit
// time micros() stands for is written to stderr as "edge <t_us> <level>", so the test can
// compare what the driver received with what the sketch was given.
#include "Arduino.h"

#include <fcntl.h>
#include <poll.h>
#include <stdio.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include <string>
#include <vector>

void setup();
void loop();

static const uint64_t START_US = (1ull << 32) - 300000;  // micros() wraps 0.3 s in
static int fd = -1;
static std::string rx, tx;
static int pin = 0;
static void (*isr)() = nullptr;
static bool frozen = false;
static uint64_t frozen_us = 0;
static struct timespec t0;

static uint64_t elapsed_us() {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return (uint64_t)(t.tv_sec - t0.tv_sec) * 1000000ull + (uint64_t)((t.tv_nsec - t0.tv_nsec) / 1000);
}
static uint64_t now64() { return frozen ? frozen_us : START_US + elapsed_us(); }

uint32_t micros() { return (uint32_t)now64(); }
unsigned long millis() { return (unsigned long)(elapsed_us() / 1000); }
int digitalRead(uint8_t) { return pin; }
void pinMode(uint8_t, uint8_t) {}
void attachInterrupt(uint8_t, void (*f)(), int) { isr = f; }
void noInterrupts() {}
void interrupts() {}

HostSerial Serial;
void HostSerial::begin(unsigned long) {}
int HostSerial::available() { return (int)rx.size(); }
int HostSerial::read() {
  if (rx.empty()) return -1;
  int c = (unsigned char)rx[0];
  rx.erase(0, 1);
  return c;
}
size_t HostSerial::write(char c) {
  tx.push_back(c);
  return 1;
}
size_t HostSerial::print(const char* s) {
  tx += s;
  return strlen(s);
}
size_t HostSerial::print(unsigned long v) {
  tx += std::to_string(v);
  return 1;
}

// The sensor: the pin changes and the interrupt runs with the clock held still, as an edge
// at one instant. The comparator module pulls its output low for light (ACTIVE_LOW).
static void edge() {
  pin ^= 1;
  frozen_us = START_US + elapsed_us();
  frozen = true;
  fprintf(stderr, "edge %llu %d\n", (unsigned long long)frozen_us, pin == LOW ? 1 : 0);
  if (isr) isr();
  frozen = false;
}

int main(int argc, char** argv) {
  if (argc < 2) {
    fprintf(stderr, "usage: sketch PTY\n");
    return 2;
  }
  fd = open(argv[1], O_RDWR | O_NOCTTY);
  if (fd < 0) {
    perror("open");
    return 1;
  }
  struct termios tio;
  tcgetattr(fd, &tio);
  cfmakeraw(&tio);
  tcsetattr(fd, TCSANOW, &tio);
  clock_gettime(CLOCK_MONOTONIC, &t0);
  pin = HIGH;  // dark
  setup();
  // 40 edges 10 ms apart from 0.2 s (the 32-bit micros() wraps at 0.3 s), a burst of 100 at
  // 0.7 s (more than the sketch's queue holds), 10 more from 0.9 s; the run ends at 1.3 s.
  std::vector<uint64_t> at;
  for (int k = 0; k < 40; k++) at.push_back(200000 + 10000 * k);
  for (int k = 0; k < 100; k++) at.push_back(700000);
  for (int k = 0; k < 10; k++) at.push_back(900000 + 10000 * k);
  size_t next = 0;
  while (elapsed_us() < 1300000) {
    while (next < at.size() && at[next] <= elapsed_us()) {
      edge();
      next++;
    }
    struct pollfd p = {fd, POLLIN, 0};
    while (poll(&p, 1, 0) > 0 && (p.revents & POLLIN)) {
      char buf[256];
      ssize_t n = ::read(fd, buf, sizeof buf);
      if (n <= 0) break;
      rx.append(buf, (size_t)n);
    }
    loop();
    if (!tx.empty()) {
      ssize_t n = ::write(fd, tx.data(), tx.size());
      if (n > 0) tx.erase(0, (size_t)n);
    }
    usleep(200);
  }
  fprintf(stderr, "done\n");
  return 0;
}
