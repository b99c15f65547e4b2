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
/* Longest accepted command line, without the newline.  The longest command in canonical form,
 * "@4294967295 SET PROFILE 179.999" + 8 x " 179.999 65535", is 143 characters. */
#define RIG_MAX_LINE 160

void rig_setup(void);
void rig_loop(void);

#ifdef __cplusplus
}
#endif

#endif
