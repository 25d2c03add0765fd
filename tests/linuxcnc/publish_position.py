#!/usr/bin/python3
"""Write LinuxCNC's actual position (machine coordinates, ``abs_act_pos``) to a file.

LinuxCNC starts it from the INI's ``[APPLICATIONS] APP`` as
``publish_position.py FILE``; it runs under the system Python (the
``linuxcnc`` module comes with LinuxCNC). Every ``PERIOD_S`` the file is
replaced (write, then rename) by one line ``x y z`` in mm, what
``xmalign sim serve --follow-position-file`` reads: the simulator's receiver
then moves with the machine LinuxCNC moves. It ends when LinuxCNC does.
"""

import os
import sys
import time

import linuxcnc

PERIOD_S = 0.005


def main():
    path = sys.argv[1]
    stat = linuxcnc.stat()
    written = None
    while True:
        try:
            stat.poll()
        except linuxcnc.error:
            return 0  # LinuxCNC has shut down
        x, y, z = stat.actual_position[:3]
        text = f"{x:.6f} {y:.6f} {z:.6f}\n"
        if text != written:
            with open(path + ".part", "w") as stream:
                stream.write(text)
            os.chmod(path + ".part", 0o644)
            os.replace(path + ".part", path)
            written = text
        time.sleep(PERIOD_S)


if __name__ == "__main__":
    sys.exit(main())
