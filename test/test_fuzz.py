"""Every CAN decoding entry point under generated frames: malformed frames are rejected with
TmclDecodeError or ignored, nothing else escapes, and none changes a motor's state (issue 17).
``youbot-fdi bench`` runs the same contract over 100,000 frames."""
from hypothesis import given, HealthCheck, settings, strategies as st
import pytest

from youbot_fdi.bench.fuzz import check_frame, fuzz_frames, FuzzTargets
from youbot_fdi.tmcm.tmcl import TmclDecodeError, TmclRequest

MAKE_TEST_FRAMES = 3000  # generated frames in make test (the benchmark: 100,000)


@pytest.fixture(scope='module')
def targets():
    made = FuzzTargets()
    yield made
    made.close()


interesting_ids = st.sampled_from([0x02, 0x11, 0x12, 0x13, 0x14, 0x15, 0x191, 0x211, 0x291,
                                   0x394, 0x181, 0x281, 0x381, 0x214, 0x7FF, 0x000])


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(can_id=st.one_of(interesting_ids, st.integers(0, 0x7FF)), data=st.binary(max_size=11))
def test_no_frame_escapes_or_changes_state_when_malformed(targets, can_id, data):
    report = check_frame(targets, can_id, data)
    assert report.violations == []


def test_generated_and_mutated_frames_keep_the_contract():
    report = fuzz_frames(MAKE_TEST_FRAMES, seed=1)
    assert report.frames == MAKE_TEST_FRAMES and report.violations == []
    assert report.malformed > MAKE_TEST_FRAMES  # most mutations are rejected somewhere


def test_the_contract_catches_a_frame_that_changes_state(targets):
    """The checker itself: an entry point that changes state and then rejects is reported."""
    def sloppy(fuzzed, can_id, data):
        fuzzed.base.modules[0].target += 1
        raise TmclDecodeError('rejected too late')
    can_id, payload = TmclRequest(0x11, 1, 0, 0, 5).to_can()
    report = check_frame(targets, can_id, payload, entry_points={'sloppy': sloppy})
    assert [v[3] for v in report.violations] == ['a malformed frame changed state']


def test_the_driver_never_stamps_a_sample_before_the_last_one():
    """The module-to-driver clock offset is re-estimated with every sample; when the estimate
    moves back, the published stamp holds instead of going backwards (the observer would count a
    backwards stamp and restart its residuals)."""
    from youbot_fdi.tmcm.process_data import MotorStatus
    made = FuzzTargets()
    try:
        driver, ids = made.driver, made.base.ids
        stamps = []
        for k, shift in enumerate([0.0, 0.0, -0.05, 0.0]):
            if driver._clock_offset is not None:
                driver._clock_offset += shift  # the estimate moves back 50 ms
            for module in driver.settings.module_ids:
                status = MotorStatus(100 * k, 10, 100, 0, 10, 2, k, 10 * (k + 1))
                for can_id, payload in zip(ids.status_ids(module), status.encode()):
                    driver._on_frame(can_id, payload, 0.0)
            stamps.append(driver.sample().stamp)
        assert all(b >= a for a, b in zip(stamps, stamps[1:])), stamps
    finally:
        made.close()
