"""fmpy's native logger proxy keeps one logger for the whole process: FMURunner must not leave it pointing at
a freed callback. Before the router, a plain fmpy instance made after a closed FMURunner crashed the process
(SIGSEGV) on its first log message; two live runners also received each other's messages.
"""
from __future__ import annotations

import subprocess
import sys
import textwrap


def test_plain_fmpy_logs_safely_after_a_closed_runner(fmu_path, tmp_path):
    code = textwrap.dedent(f"""
        import gc, fmpy
        from fmpy.fmi2 import FMU2Slave
        from fmusa.fmi.runner import FMURunner
        with FMURunner({str(fmu_path)!r}) as r:
            r.run({{"c_y": 8e5}}, stop_time=0.1, step=0.05, outputs=["y"])
        del r
        gc.collect()
        unzipped = fmpy.extract({str(fmu_path)!r}, {str(tmp_path / 'u')!r})
        md = fmpy.read_model_description(unzipped)
        vr = {{v.name: v.valueReference for v in md.modelVariables}}
        fmu = FMU2Slave(guid=md.guid, unzipDirectory=unzipped, modelIdentifier=md.coSimulation.modelIdentifier,
                        instanceName="plain")
        fmu.instantiate()
        fmu.setupExperiment(startTime=0.0)
        fmu.enterInitializationMode()
        fmu.exitInitializationMode()
        try:
            fmu.setReal([vr["c_y"]], [1.0])   # refused after initialisation: the FMU logs why
        except Exception:
            pass
        fmu.freeInstance()
        print("survived")
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "survived" in proc.stdout


def test_two_live_runners_keep_their_messages_apart(fmu_path):
    from fmusa.fmi.runner import FMURunner

    with FMURunner(fmu_path) as a, FMURunner(fmu_path) as b:
        a.run({"c_y": 8e5}, stop_time=0.1, step=0.05, outputs=["y"])
        b.run({"c_y": 8e5}, stop_time=0.1, step=0.05, outputs=["y"])
        a.messages.clear()
        b.messages.clear()
        try:
            a.run({"c_y": -1.0}, stop_time=0.1, step=0.05, outputs=["y"])   # a bad value: the FMU says why
        except Exception:
            pass
        assert a.messages, "runner a got no message for its own refused parameter"
        assert not b.messages, f"runner b got runner a's messages: {list(b.messages)}"
