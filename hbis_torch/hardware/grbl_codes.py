"""Meanings of the GRBL 1.1 ``error:N`` and ``ALARM:N`` codes.

Paraphrased from the GRBL 1.1 interface documentation (gnea/grbl, ``doc/markdown/interface.md``
and ``doc/csv/*_codes_en_US.csv``). Codes a controller sends that are not in the GRBL 1.1 tables
(forks such as grblHAL add more) get a generic meaning that says so.
"""

from __future__ import annotations

ERROR_CODES: dict[int, str] = {
    1: "Expected command letter: a G-code word has a value but no letter",
    2: "Bad number format: a value is missing or is not a valid number",
    3: "Invalid statement: the '$' system command is unknown or unsupported",
    4: "Value < 0: a negative value was given where a positive one is required",
    5: "Setting disabled: homing is not enabled in the settings ($22)",
    6: "Value < 3 usec: the step pulse time must be at least 3 microseconds",
    7: "EEPROM read fail: settings were reset to their defaults",
    8: "Not idle: this '$' command is only accepted while the controller is Idle",
    9: "G-code lock: G-code is refused in the Alarm or Jog state (unlock with $X or home with $H)",
    10: "Homing not enabled: soft limits need homing to be enabled",
    11: "Line overflow: the line is longer than the controller accepts and was not run",
    12: "Step rate > 30kHz: the setting would exceed the highest supported step rate",
    13: "Check Door: the safety door is open",
    14: "Line length exceeded: the build info or startup line is too long to store",
    15: "Travel exceeded: the jog target is outside the machine travel; the jog was ignored",
    16: "Invalid jog command: the jog has no '=' or contains a forbidden G-code",
    17: "Setting disabled: laser mode needs PWM output",
    20: "Unsupported command: the block contains an unsupported or invalid G-code",
    21: "Modal group violation: two G-codes of the same modal group in one block",
    22: "Undefined feed rate: no feed rate has been set",
    23: "Invalid gcode ID:23: a G-code in the block needs an integer value",
    24: "Invalid gcode ID:24: two G-codes in the block both need the axis words",
    25: "Invalid gcode ID:25: a G-code word is repeated in the block",
    26: "Invalid gcode ID:26: a G-code needs axis words but the block has none",
    27: "Invalid gcode ID:27: the N line number is out of range",
    28: "Invalid gcode ID:28: a G-code is missing a required P or L value",
    29: "Invalid gcode ID:29: work coordinate systems G59.1-G59.3 are not supported",
    30: "Invalid gcode ID:30: G53 is only allowed with the G0 and G1 motion modes",
    31: "Invalid gcode ID:31: axis words in a block where no command uses them",
    32: "Invalid gcode ID:32: a G2/G3 arc has no axis word in the selected plane",
    33: "Invalid gcode ID:33: the motion target is invalid",
    34: "Invalid gcode ID:34: the arc radius is invalid",
    35: "Invalid gcode ID:35: a G2/G3 arc has no offset word in the selected plane",
    36: "Invalid gcode ID:36: the block has unused value words",
    37: "Invalid gcode ID:37: G43.1 tool offset is not on the configured tool-length axis",
    38: "Invalid gcode ID:38: the tool number is larger than supported",
}

ALARM_CODES: dict[int, str] = {
    1: "Hard limit: a limit switch triggered; position is likely lost, re-homing is advised",
    2: "Soft limit: the motion target exceeds the machine travel; position kept, may be unlocked",
    3: "Abort during cycle: reset while moving; position is likely lost, re-homing is advised",
    4: "Probe fail: the probe was not in its expected initial state",
    5: "Probe fail: the probe made no contact within the programmed travel",
    6: "Homing fail: the homing cycle was reset",
    7: "Homing fail: the safety door opened during homing",
    8: "Homing fail: pulling off did not clear the limit switch (check pull-off $27 and wiring)",
    9: "Homing fail: no limit switch found within the search distance (check wiring and $130/$131)",
    10: "Homing fail: the second limit switch of a dual-motor axis did not trigger within the search distance after the first",
}


def error_meaning(code: int) -> str:
    """The meaning of GRBL ``error:code`` (a generic line for codes outside the 1.1 table)."""
    return ERROR_CODES.get(int(code), f"unknown error code {int(code)} (not in the GRBL 1.1 table)")


def alarm_meaning(code: int) -> str:
    """The meaning of GRBL ``ALARM:code`` (a generic line for codes outside the 1.1 table)."""
    return ALARM_CODES.get(int(code), f"unknown alarm code {int(code)} (not in the GRBL 1.1 table)")
