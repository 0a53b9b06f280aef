"""bench/discovery.py files a case's SITL flights in --out under a name without a folder: a bundled vehicle's
name, or a vehicle file's stem with a digest of its content. Until session 75 a case given a vehicle file's
path wrote its flights beside that file, wherever it was, and --out never saw them."""

from __future__ import annotations

import shutil
from pathlib import Path

from bench_module import bench_module

VEHICLES = Path(__file__).resolve().parent.parent / "bench" / "vehicles"


def test_a_vehicle_files_flights_are_named_inside_out_and_by_its_content(tmp_path: Path) -> None:
    bench = bench_module("discovery.py", "bench_discovery")
    mine = tmp_path / "elsewhere" / "my-quad.yaml"
    mine.parent.mkdir()
    shutil.copy(VEHICLES / "heavy-650.yaml", mine)
    name = bench.flight_name(str(mine))
    out = tmp_path / "out"
    assert (out / f"{name}.tlog").parent == out  # no folder in the name: the flight lands in --out
    assert name.startswith("my-quad-") and name != bench.flight_name("my-quad")
    assert bench.flight_name(str(mine)) == name  # the same file: the flights --reuse-flights reads
    mine.write_text(mine.read_text() + "\n# edited\n")
    assert bench.flight_name(str(mine)) != name  # an edited vehicle does not reuse the old one's flights
    assert bench.flight_name("heavy-650") == "heavy-650"  # a bundled vehicle keeps its name
