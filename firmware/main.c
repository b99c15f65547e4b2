/* Entry point of the Makefile build; the Arduino sketch rig_servo.ino does the same. */
#include "core/rig.h"

int main(void)
{
    rig_setup();
    for (;;)
        rig_loop();
}
