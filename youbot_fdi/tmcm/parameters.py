"""TMCM axis/global parameter numbers and status flags the youBot base uses.

Numbers as the youBot driver uses them (youbot_driver YouBotJointParameter*.cpp, firmware 2.0);
sources in ../shared/reference/tmcm_youbot_facts.md §2 and §3.4.
"""
import enum


class AxisParameter(enum.IntEnum):
    """Axis parameters (SAP/GAP type numbers)."""

    TARGET_POSITION = 0  # [ticks]
    ACTUAL_POSITION = 1  # [ticks]; SAP 1 with value 0 zeroes the encoder
    TARGET_VELOCITY = 2  # [rpm]
    ACTUAL_VELOCITY = 3  # [rpm]
    MAX_POSITIONING_VELOCITY = 4  # [rpm]
    MAX_CURRENT = 6  # [mA]
    ACCELERATION = 11  # [rpm/s]
    INITIALIZED = 15  # sine commutation done
    THERMAL_WINDING_TIME = 25  # [ms]
    I2T_LIMIT = 26  # [mA² s / 1000] here: the I²t sum at which the flag trips
    I2T_SUM = 27  # read-only
    I2T_EXCEED_COUNTER = 28
    CLEAR_I2T_FLAG = 29
    PID_CONTROL_TIME = 133  # [ms]
    CURRENT_P = 172
    CURRENT_I = 173
    ACTUAL_CURRENT = 150  # [mA]
    SUPPLY_VOLTAGE = 151  # [0.01 V]
    TARGET_CURRENT = 155  # [mA]
    ERROR_FLAGS = 156
    CLEAR_TIMEOUT_FLAG = 158
    VELOCITY_P = 234  # velocity PID set 2 (always used with threshold 0) [mA per rpm * 1000]
    VELOCITY_I = 235  # [mA per (rpm s) * 1000]
    ENCODER_RESOLUTION = 250  # [ticks per motor revolution]
    MOTOR_POLES = 253


class GlobalParameter(enum.IntEnum):
    """Global parameters (SGP/GGP type numbers, bank 0)."""

    MOTOR_CONTROLLER_TIMEOUT = 90  # [ms]; 0 disables


class ErrorFlag(enum.IntFlag):
    """Process-data error/status flags of firmware 2.0 (youbot_driver MailboxErrorFlags)."""

    NONE = 0
    OVER_CURRENT = 0x1
    UNDER_VOLTAGE = 0x2
    OVER_VOLTAGE = 0x4
    OVER_TEMPERATURE = 0x8
    MOTOR_HALTED = 0x10
    HALL_SENSOR_ERROR = 0x20
    VELOCITY_MODE = 0x200
    POSITION_MODE = 0x400
    TORQUE_MODE = 0x800
    POSITION_REACHED = 0x4000
    MODULE_INITIALIZED = 0x8000
    TIMEOUT = 0x10000
    I2T_EXCEEDED = 0x20000


#: Flags that mean something is wrong (the others describe the mode).
ERROR_FLAGS = (ErrorFlag.OVER_CURRENT | ErrorFlag.UNDER_VOLTAGE | ErrorFlag.OVER_VOLTAGE
               | ErrorFlag.OVER_TEMPERATURE | ErrorFlag.HALL_SENSOR_ERROR | ErrorFlag.TIMEOUT
               | ErrorFlag.I2T_EXCEEDED)


def describe_flags(flags):
    """Names of the set flags, e.g. ``['VELOCITY_MODE', 'TIMEOUT']``."""
    return [flag.name for flag in ErrorFlag if flag and flags & flag]
