"""study.precision: bf16 runs paired with fp32 runs of the same task and seed."""


def test_bf16_pairs_are_the_raw_scores_differences():
    """study.precision pairs each bf16 run with the fp32 run of the same task and seed: checked against the
    JSONs read here directly."""
    import json

    from study import precision
    from study.summary import HERE

    changes = precision.paired(precision.BF16_ARM, precision.FP32_ARM)
    assert changes, "no bf16 runs to pair"
    for task, by_seed in changes.items():
        for seed, change in by_seed.items():
            read = lambda arm: json.loads((HERE / "results" / arm / task / f"seed{seed}.json").read_text())
            expected = read("bf16_preset")["final_normalized_score_mean"] - read("alpha1")["final_normalized_score_mean"]
            assert change == expected
            assert read("bf16_preset")["overrides"] == ["precision=bf16"]
