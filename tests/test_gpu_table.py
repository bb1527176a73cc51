"""benchmarks.gpu_table: the GPU check's speeds, read from progress bars and hand-computed here."""
import json

from benchmarks.gpu_table import render, seconds, stage_progress

BARS = ("stage 1: TS-IDM beta=1:  10%|#         | 300/3000 [00:05<00:45, 60.00it/s]\r"
        "stage 1: TS-IDM beta=1: 100%|##########| 3000/3000 [00:24<00:00, 125.0it/s, loss=0.05]\n"
        "latent scale: RMS spread 1.0\n"
        "stage 2: value + guide, 5 seeds:  18%|#8        | 880/5000 [01:11<03:50, 17.89it/s, score=43.1, eval_s=12]\r")


def test_seconds_reads_minutes_and_hours():
    assert seconds("02:46") == 166
    assert seconds("1:02:46") == 3766


def test_stage_progress_keeps_each_stage_s_last_bar():
    assert stage_progress(BARS) == {"stage 1": (3000, 3000, 24), "stage 2": (880, 5000, 71)}


def test_render_uses_the_last_run_of_a_name_and_a_finished_run_s_score(tmp_path):
    (tmp_path / "walls.txt").write_text("study_seed0 1 9\nstudy_seed0 0 95\nstudy_seeds5 124 150\n")
    (tmp_path / "gpu.txt").write_text("Some GPU, 1 MiB, 1.0\n")
    (tmp_path / "tests.txt").write_text("....\n4 passed in 3.0s\n")
    (tmp_path / "study_seed0.log").write_text(BARS.replace(", 5 seeds", ""))
    (tmp_path / "study_seed0").mkdir()
    (tmp_path / "study_seed0" / "results.json").write_text(json.dumps({"final_normalized_score_mean": 47.26}))
    (tmp_path / "study_seeds5.log").write_text(BARS)
    table = render(tmp_path)
    assert "4 passed in 3.0s" in table
    rows = [line for line in table.splitlines() if line.startswith("| study")]
    # 3000 / 24 = 125.0 and 880 / 71 = 12.39...: the means over the elapsed time, not tqdm's smoothed rate
    assert rows[0].split(" | ")[1:] == ["0", "95", "125.0 (3,000/3,000 steps in 24 s)",
                                        "12.4 (880/5,000 steps in 71 s)", "12", "47.3 |"]
    assert rows[1].split(" | ")[1:3] == ["124", "150"] and rows[1].endswith("did not finish |")


def test_bars_without_a_rate_or_a_description_and_hours_elapsed():
    log = ("stage 1:  0%|          | 0/36000 [00:00<?, ?it/s]\r"
           "stage 2: value + guide: 50%|#####     | 50000/100000 [1:02:46<?, ?it/s]\n")
    assert stage_progress(log) == {"stage 1": (0, 36000, 0), "stage 2": (50000, 100000, 3766)}


def test_a_check_that_stopped_early_renders_without_its_files(tmp_path):
    table = render(tmp_path)
    assert "machine: not run" in table and "there: not run" in table
    assert "Not measured: the check wrote no compile_speed.json." in table
    assert not [line for line in table.splitlines() if line.startswith("| study")]


def test_speed_table_gives_each_stage_s_steps_per_second_by_mode(tmp_path):
    figures = {"args": {"device": "cuda", "seeds": "1", "steps": "200", "repeats": "3", "warmup": "30"},
               "stages": {"tsidm": {"eager": {"steps_per_s": 250.4, "warmup_s": 0.4},
                                    "cudagraphs": {"steps_per_s": 1999.6, "warmup_s": 2.2}},
                          "policy": {"eager": {"steps_per_s": 100.0, "warmup_s": 0.3}}}}
    (tmp_path / "compile_speed.json").write_text(json.dumps(figures))
    table = render(tmp_path)
    assert "| stage | eager | `compile.cudagraphs=true` |" in table
    assert "| 1 (TS-IDM) | 250 (0 s) | 2,000 (2 s) |" in table
    assert "| 2 (V + guide) | 100 (0 s) | — |" in table
