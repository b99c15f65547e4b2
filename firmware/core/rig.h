/* Servo-rig firmware core for the ATmega328P (Arduino Uno / Nano at 16 MHz).
 * The Makefile's main.c and the Arduino sketch rig_servo.ino both just call
 * rig_setup() once and rig_loop() forever.  Protocol: firmware/PROTOCOL.md. */
#ifndef RIG_H
#define RIG_H

#ifdef __cplusplus
extern "C" {
#endif

#define RIG_PROTOCOL_VERSION 1
#define RIG_FIRMWARE_VERSION "1.0.0"
#define RIG_FRAME_US 20000UL          /* 50 Hz servo frame */
#define RIG_TRIGGER_US 1000U          /* trigger-out pulse width */
#define RIG_MAX_LINE 128              /* longest accepted command line, without newline */

void rig_setup(void);
void rig_loop(void);

#ifdef __cplusplus
}
#endif

#endif
