// Servo-rig firmware for Arduino Uno / Nano (ATmega328P, 16 MHz), for Arduino IDE users.
//
// All the logic lives in the plain-C core (firmware/core), shared with the Makefile build;
// `src/` next to this sketch is a link to ../core (run `make -C firmware sketch` to replace it
// by a copy if your checkout does not keep symlinks).  The core drives Timer1 and the UART
// itself, so this sketch must not use Serial or the Servo library.
// Wiring: D9 scene servo signal, D10 turntable servo signal, D8 trigger output.
// Protocol: firmware/PROTOCOL.md (115200 baud, line based).

#include "src/rig.h"

void setup() {
  rig_setup();
}

void loop() {
  rig_loop();
}
