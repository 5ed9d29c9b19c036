"""``driver_shim`` node: /wheel_commands -> TMCM process data over CAN -> /joint_states, /diagnostics.

``ros2 run youbot_fdi driver_shim --ros-args --params-file config/driver_shim.yaml``

Topics (CONTRACT.md, driver convention): subscribes ``/wheel_commands`` (JointState: ``velocity``
[rad/s] or ``effort`` [N·m], matched by joint name); publishes ``/joint_states`` (position [rad],
velocity [rad/s], effort [N·m] from the measured current) once per process-data cycle, every
wheel's readings from that cycle, stamped with the cycle's time (NaN for a module that did not
answer within the cycle: missing data, never its previous value), and ``/diagnostics`` (one status
per wheel module and one for the bus, with the cycle's period and lateness, p50/p99/max).
Services ``~/switch_on_motors`` and ``~/switch_off_motors`` (std_srvs/Trigger), and per wheel
``~/switch_off_motor_<w>`` (``<w>`` the wheel suffix, e.g. ``fl``): that wheel's motor off (TMCL
MST, then 0 mA) until ``~/switch_on_motors``; a fault reaction of the kinematics bridge. The
services answer at once, without holding the process-data cycle for the modules' TMCL replies,
which are logged when they come (or do not, within ``tmcl_timeout``).
A command older than ``command_timeout`` is replaced by zero speed (watchdog).

``realtime_priority`` and ``cpu_cores`` give the shim's cycle and CAN threads SCHED_FIFO priority
and a CPU affinity where the OS permits (docs/tmcm.md, "Cycle timing"); off by default.
"""
import sys

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from youbot_fdi.model.profile import load_model
from youbot_fdi.naming import wheel_suffix
from youbot_fdi.nodes.common import (declare_settings, health_to_diagnostics,
                                     now_seconds, SENSOR_QOS, seconds_to_stamp, spin_nodes,
                                     STREAM_QOS)
from youbot_fdi.tmcm.driver import BaseDriver, CommandKind, DriverSettings
from youbot_fdi.tmcm.tmcl import TmclCommand
from youbot_fdi.tmcm.transport import open_bus
from youbot_fdi.timing import apply_scheduling, parse_cores
from youbot_fdi.topics import DIAGNOSTICS, JOINT_STATES, WHEEL_COMMANDS

NODE_NAME = 'driver_shim'


class DriverShimNode(Node):
    """Thin adapter: ROS messages <-> :class:`~youbot_fdi.tmcm.driver.BaseDriver`."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        self.settings = declare_settings(self, DriverSettings)
        self.model = load_model(self.settings.profile)
        self.names = list(self.model.wheel_names)
        self.hardware_ids = {name: f'tmcm-0x{module:02x}' for name, module in
                             zip(self.names, self.settings.module_ids)}
        # Before the CAN threads start, so that they inherit priority and affinity.
        for line in apply_scheduling(self.settings.realtime_priority,
                                     parse_cores(self.settings.cpu_cores)):
            self.get_logger().info(line)
        self.get_logger().info(
            f'a cycle later than {self.settings.controller_timeout:g} s stops the modules '
            '(their controller timeout, GP 90); late cycles are counted on /diagnostics')
        self.joint_pub = self.create_publisher(JointState, JOINT_STATES, STREAM_QOS)
        bus = open_bus(self.settings.can_interface, self.settings.can_channel)
        self.driver = BaseDriver(self.model, bus, self.settings, clock=lambda: now_seconds(self),
                                 owns_bus=True, on_sample=self.publish_sample)
        self.diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS, 10)
        self.create_subscription(JointState, WHEEL_COMMANDS, self.on_command, SENSOR_QOS)
        self.create_service(Trigger, '~/switch_on_motors', self.on_switch_on)
        self.create_service(Trigger, '~/switch_off_motors', self.on_switch_off)
        for name in self.names:
            self.create_service(Trigger, f'~/switch_off_motor_{wheel_suffix(name)}',
                                lambda request, response, name=name: self.on_motor_off(name, response))
        self._configured = False
        self._recoveries_told = 0
        self.create_timer(1.0 / self.settings.cycle_rate, self.on_cycle)
        self.create_timer(1.0 / self.settings.diagnostics_rate, self.publish_diagnostics)

    def on_command(self, msg):
        """Match the command by joint name and hand it to the driver; reject bad ones visibly."""
        index = {name: i for i, name in enumerate(msg.name)}
        missing = [n for n in self.names if n not in index]
        if missing:
            self.driver.rejected_commands += 1
            self.driver.last_rejection = f'/wheel_commands lacks joints {missing}'
            self.get_logger().warning(self.driver.last_rejection, throttle_duration_sec=2.0)
            return
        for kind, array in ((CommandKind.VELOCITY, msg.velocity), (CommandKind.EFFORT, msg.effort)):
            if len(array) == 0:
                continue
            if len(array) != len(msg.name):
                self.driver.rejected_commands += 1
                self.driver.last_rejection = (f'/wheel_commands {kind.value} has {len(array)} values '
                                              f'for {len(msg.name)} names')
                self.get_logger().warning(self.driver.last_rejection, throttle_duration_sec=2.0)
                return
            try:
                self.driver.set_command(kind, [array[index[n]] for n in self.names])
            except ValueError as err:
                self.get_logger().warning(str(err), throttle_duration_sec=2.0)
            return
        self.driver.rejected_commands += 1
        self.driver.last_rejection = '/wheel_commands carries neither velocity nor effort'

    def on_cycle(self):
        if not self._configured:
            self._configured = True
            failed = self.driver.configure_modules()
            if failed:
                self.get_logger().warning(f'modules did not answer configuration: {failed}')
        self.driver.cycle()
        self.report_mailbox()
        if self.driver.timeout_recoveries > self._recoveries_told:
            self._recoveries_told = self.driver.timeout_recoveries
            self.get_logger().warning(
                'a module stopped on its controller timeout (no process data for '
                f'{self.settings.controller_timeout:g} s: this cycle ran late) and was cleared '
                f'({self._recoveries_told} so far)', throttle_duration_sec=2.0)

    def publish_sample(self, sample):
        """One /joint_states message per closed cycle (the driver calls it in cycle order, from
        the CAN receive thread or from the cycle timer)."""
        msg = JointState()
        msg.header.stamp = seconds_to_stamp(sample.stamp)
        msg.name = self.names
        msg.position = sample.position.tolist()
        msg.velocity = sample.velocity.tolist()
        msg.effort = sample.effort.tolist()
        self.joint_pub.publish(msg)

    def publish_diagnostics(self):
        array = health_to_diagnostics(self, self.driver.health(), NODE_NAME, self.hardware_ids,
                                      f'can:{self.settings.can_channel}')
        self.diag_pub.publish(array)

    def on_switch_on(self, _request, response):
        """Answers at once: the modules' flags are cleared without holding the cycle for their
        replies; a module that does not answer is logged by :meth:`report_mailbox`."""
        self.driver.motors_on()
        response.success = True
        response.message = 'motors on (a module that does not answer the flags\' clearing is logged)'
        return response

    def on_switch_off(self, _request, response):
        self.driver.motors_off()
        response.success, response.message = True, 'motors off (0 mA, coasting)'
        return response

    def on_motor_off(self, name, response):
        """Answers at once (the stop frame sent, 0 mA from the next cycle): waiting for the
        module's reply here would hold the cycle. The reply is logged by :meth:`report_mailbox`."""
        self.driver.motor_off(name)
        response.success = True
        response.message = f'{name}: motor off (stop frame sent, 0 mA from the next cycle, coasting)'
        self.get_logger().warning(response.message)
        return response

    def report_mailbox(self):
        """Log what the modules answered to the requests the services sent without waiting
        (settled since the last cycle)."""
        for outcome in self.driver.mailbox_outcomes():
            stopping = outcome.command is TmclCommand.MST
            if stopping and outcome.ok:
                self.get_logger().info(f'{outcome.wheel}: the module confirmed the stop')
            elif stopping:
                said = ('refused the stop' if outcome.answered else
                        f'did not confirm the stop within {self.settings.tmcl_timeout:g} s')
                self.get_logger().warning(f'{outcome.wheel}: the module {said}; 0 mA stands')
            elif not outcome.ok:
                said = ('refused clearing its flags' if outcome.answered else
                        f'did not answer the clearing of its flags within {self.settings.tmcl_timeout:g} s')
                self.get_logger().warning(f'{outcome.wheel}: the module {said}: a timeout or I²t '
                                          'flag may still hold it')

    def close(self):
        self.driver.close()


def main(args=None):
    """Entry point of ``ros2 run youbot_fdi driver_shim``."""
    return spin_nodes([DriverShimNode], args=args)


if __name__ == '__main__':
    sys.exit(main())


