"""Make docs/img/dashboard.png (and dashboard-plan.png): the dashboard replaying a small room, in headless Chromium.

Run from the repository root: ``.venv/bin/python docs/img/dashboard.py``. The
room is tests/_dashboard_room.py's (three sensors, a fixed emitter and a tag
on a circle, each sensor's angles and amplitudes, a reflection into s2); the
3-D view is software-rendered (WebGL through SwiftShader).
"""
from __future__ import annotations

import base64
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "src"))
OUT = Path(__file__).resolve().parent


def main():
    import os

    from _dashboard_room import write_room
    from browser import Chromium

    from psdcal.cli._events import append_event, event

    env = dict(os.environ, PYTHONPATH=str(REPO / "src"))
    with tempfile.TemporaryDirectory() as d:
        room = write_room(d, duration_s=40.0, sensor_rows=True)
        plan = Path(d) / "plan.csv"
        subprocess.run([sys.executable, "-m", "psdcal.cli", "plan", "--sensors", str(room["sensors"]), "--room-m", "6", "4",
                        "3", "--height-m", "1.0", "--grid-mm", "200", "-o", str(Path(d) / "plan.png"), "--csv", str(plan)],
                       check=True, env=env, capture_output=True)
        events = Path(d) / "events.jsonl"
        append_event(events, event("3 emitters fix the pose exactly (no redundancy): the fit cannot be checked",
                                   command="pose"))
        args = [room["rows"], "--sensors", room["sensors"], "--emitters", room["emitters"], "--events", events,
                "--plan", plan, "--replay", "--speed", "1", "--port", "0", "--title", "psdcal dashboard: demo room"]
        for s in ("s1", "s2", "s3"):
            args += ["--sensor-rows", f"{s}={room[s + '_angles']}", "--sensor-rows", f"{s}={room[s + '_amp']}"]
        proc = subprocess.Popen([sys.executable, "-m", "psdcal.cli", "dashboard", *map(str, args)],
                                stdout=subprocess.PIPE, text=True, env=env)
        try:
            url = re.search(r"(http://\S+)", proc.stdout.readline()).group(1)
            with Chromium(timeout_s=120, extra_flags=("--enable-unsafe-swiftshader", "--use-angle=swiftshader")) as b:
                b.open_page(1400, 1180)
                b.load(url)
                while float(b.evaluate("document.body.dataset.viewT || 0")) < 6.2:
                    time.sleep(0.2)
                b.evaluate("document.getElementById('pause').click()")
                time.sleep(3)
                (OUT / "dashboard.png").write_bytes(b.screenshot())
                b.evaluate("document.getElementById('planlayer').click()")
                time.sleep(3)
                r = b.evaluate("JSON.stringify(document.getElementById('top').getBoundingClientRect())")
                import json

                r = json.loads(r)
                png = b.send("Page.captureScreenshot", {"format": "png", "clip": {
                    "x": r["x"], "y": r["y"], "width": r["width"], "height": r["height"], "scale": 1}})["data"]
                (OUT / "dashboard-plan.png").write_bytes(base64.b64decode(png))
        finally:
            proc.terminate()
            proc.wait(timeout=10)
    print(f"wrote {OUT / 'dashboard.png'} and {OUT / 'dashboard-plan.png'}")


if __name__ == "__main__":
    main()
