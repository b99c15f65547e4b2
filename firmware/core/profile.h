/* Minimum-jerk motion profile in integer arithmetic (Q16), shared by the firmware and its
 * tests.  The formulas are exactly those of evdnerf_ros/sim/servo_profile.py
 * (`move_command_mdeg`, `RunProfile.command_mdeg`); the tests compare them value by value.
 * Plain C99, no AVR headers: it also compiles on the host. */
#ifndef RIG_PROFILE_H
#define RIG_PROFILE_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define RIG_ONE_Q16 65536UL
#define RIG_MAX_SEGMENTS 8

typedef struct {
    int32_t angle_mdeg;   /* target of this segment, millidegrees */
    uint16_t ms;          /* duration, 1..65535 ms */
} rig_segment_t;

/* s(e/D) in Q16 (0..65536), e and D in the same unit (us), D > 0. */
uint32_t rig_min_jerk_q16(uint32_t e_us, uint32_t d_us);

/* Commanded angle (mdeg) of a MOVE a0 -> a1 over d_us at elapsed e_us. */
int32_t rig_move_command_mdeg(uint32_t e_us, uint32_t d_us, int32_t a0, int32_t a1);

/* Commanded angle of a segment list started at elapsed 0 from a0 (RunProfile.command_mdeg);
 * *finished is set to 1 once e_us is at or past the end of the last segment. */
int32_t rig_profile_command_mdeg(uint32_t e_us, int32_t a0, const rig_segment_t *seg,
                                 uint8_t nseg, uint8_t *finished);

/* Pulse width in Timer1 ticks (0.5 us) for an angle 0..180000 mdeg mapped linearly onto
 * pulse_min_us..pulse_max_us, rounded to the nearest tick. */
uint16_t rig_pulse_ticks(int32_t mdeg, uint16_t pulse_min_us, uint16_t pulse_max_us);

#ifdef __cplusplus
}
#endif

#endif
