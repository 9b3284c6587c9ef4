"""A collector killed with SIGKILL at random instants loses nothing committed and resumes."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np

from twist_data.reader import open_dataset
from twist_data.synth import SynthConfig, synthetic_episode
from twist_data.verify import verify_dataset

CONFIG = SynthConfig(episodes=12, steps=120, views=2, image_size=32, seed=5)

COLLECTOR = textwrap.dedent("""
    import sys
    from pathlib import Path
    from twist_data.storage import StorageLayout
    from twist_data.synth import SynthConfig, synth_spec, synthetic_episode
    from twist_data.writer import ShardWriter

    out = Path(sys.argv[1])
    config = SynthConfig(episodes=12, steps=120, views=2, image_size=32, seed=5)
    layout = StorageLayout(steps_per_file=256)  # episodes straddle files: partial rewrites
    if (out / "c.zarr").exists():
        writer = ShardWriter.resume(out / "c.zarr")
    else:
        writer = ShardWriter.create(out, "c", synth_spec(2, 32), layout)
    while writer.n_episodes < config.episodes:
        writer.append(*synthetic_episode(config, writer.n_episodes))
        print(writer.n_episodes, flush=True)
""")


def run_until_killed(script: Path, out: Path, delay: float) -> int:
    """Start the collector, SIGKILL it ``delay`` s after its first commit; last printed count."""
    proc = subprocess.Popen([sys.executable, str(script), str(out)], stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdout is not None
    first = proc.stdout.readline()
    if not first:
        proc.wait()
        return -1
    time.sleep(delay)
    proc.kill()
    rest = proc.stdout.read()
    proc.wait()
    lines = [first, *rest.split()]
    return int(lines[-1])


def test_sigkill_at_random_instants_then_resume(tmp_path: Path) -> None:
    script = tmp_path / "collector.py"
    script.write_text(COLLECTOR)
    out = tmp_path / "ds"
    expected = [synthetic_episode(CONFIG, i)[0] for i in range(CONFIG.episodes)]
    rng = np.random.default_rng(0)
    kills = 0
    for _ in range(6):
        printed = run_until_killed(script, out, delay=float(rng.uniform(0.0, 0.4)))
        if printed < 0:
            break
        kills += 1
        report = verify_dataset(out)
        assert report.ok, [str(p) for p in report.problems]
        ds = open_dataset(out)
        # the kill may land after a commit but before its print
        assert ds.n_episodes in (printed, printed + 1)
        last = ds.episode(ds.n_episodes - 1)
        np.testing.assert_array_equal(last.image, expected[ds.n_episodes - 1].image)
        if ds.n_episodes == CONFIG.episodes:
            break
    assert kills >= 2
    subprocess.run([sys.executable, str(script), str(out)], check=True, capture_output=True)
    assert verify_dataset(out).ok
    ds = open_dataset(out)
    assert ds.n_episodes == CONFIG.episodes
    for i, episode in ds.iter_episodes():
        for key, value in expected[i].arrays().items():
            np.testing.assert_array_equal(episode.arrays()[key], value, err_msg=f"{i} {key}")
