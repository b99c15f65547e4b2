/* Integer minimum-jerk profile; see profile.h and evdnerf_ros/sim/servo_profile.py. */
#include "profile.h"

uint32_t rig_min_jerk_q16(uint32_t e_us, uint32_t d_us)
{
    uint64_t u, u3, p;
    if (e_us == 0)
        return 0;
    if (e_us >= d_us)
        return RIG_ONE_Q16;
    u = ((uint64_t)e_us * RIG_ONE_Q16) / d_us;           /* tau in Q16, < 2^16 */
    u3 = (u * u * u) >> 24;                              /* tau^3 in Q24 */
    /* 10 - 15 tau + 6 tau^2 in Q32: positive, so modular unsigned arithmetic is exact */
    p = 10ULL * RIG_ONE_Q16 * RIG_ONE_Q16 - 15ULL * RIG_ONE_Q16 * u + 6ULL * u * u;
    return (uint32_t)((u3 * p) >> 40);
}

int32_t rig_move_command_mdeg(uint32_t e_us, uint32_t d_us, int32_t a0, int32_t a1)
{
    int64_t d = (int64_t)(a1 - a0) * (int64_t)rig_min_jerk_q16(e_us, d_us);
    uint64_t mag = (uint64_t)(d < 0 ? -d : d);
    int32_t q = (int32_t)((mag + (RIG_ONE_Q16 >> 1)) >> 16);   /* round half away from 0 */
    return d >= 0 ? a0 + q : a0 - q;
}

int32_t rig_profile_command_mdeg(uint32_t e_us, int32_t a0, const rig_segment_t *seg,
                                 uint8_t nseg, uint8_t *finished)
{
    uint32_t start = 0;
    uint8_t k;
    for (k = 0; k < nseg; k++) {
        uint32_t d = (uint32_t)seg[k].ms * 1000UL;
        if (e_us < start + d) {
            *finished = 0;
            return rig_move_command_mdeg(e_us - start, d, a0, seg[k].angle_mdeg);
        }
        start += d;
        a0 = seg[k].angle_mdeg;
    }
    *finished = 1;
    return a0;
}

uint16_t rig_pulse_ticks(int32_t mdeg, uint16_t pulse_min_us, uint16_t pulse_max_us)
{
    uint32_t span2 = 2UL * (uint32_t)(pulse_max_us - pulse_min_us);
    if (mdeg < 0)
        mdeg = 0;
    if (mdeg > 180000L)
        mdeg = 180000L;
    return (uint16_t)(2U * pulse_min_us + ((uint32_t)mdeg * span2 + 90000UL) / 180000UL);
}
