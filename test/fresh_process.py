"""Run a live demo in a fresh interpreter, as `youbot-fdi demo` runs on a robot PC.

By the live tests the pytest process has run three hundred tests and holds a quarter of a million
objects; a full (generation 2) garbage collection then takes 0.1–0.17 s on this 2-core machine
(measured with ``gc.callbacks`` over a whole run). The demo's driver shim shares its process, so
one such pause plus a late cycle stalls /joint_states past the 0.2 s comm timeout: a true base
``comm_loss`` of that process, not of the demo. A user's demo, and every node on the robot, starts
with a small heap; the tests run the demo the same way.
"""
import multiprocessing


def in_fresh_process(function, *args):
    """``function(*args)`` in a newly spawned interpreter; returns its (picklable) result and
    raises what it raises. ``function`` must be importable (a module-level name)."""
    with multiprocessing.get_context('spawn').Pool(1) as pool:
        return pool.apply(function, args)


def run_demo_fresh(plan):
    """:func:`youbot_fdi.nodes.demo.run_demo` of ``plan`` in a fresh interpreter."""
    return in_fresh_process(_run_demo, plan)


def _run_demo(plan):
    from youbot_fdi.nodes.demo import run_demo
    return run_demo(plan)
