import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import InstantiationException

from tests.test_readme import ROOT
from train import run


def _cfg(*overrides):
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "configs")):
        return compose(config_name="train", overrides=list(overrides))


def test_benchmark_mode_runs_the_shadow_benchmark_shrunk():
    rows, path = run(_cfg("mode=benchmark", "benchmark.height=30", "benchmark.width=40", "benchmark.write=false"))
    assert path is None and rows[-1]["light"] == "**mean**"
    assert 0.8 < rows[-1]["epipolar_agree"] <= 1.0


def test_paper_table_runs_shrunk_with_the_published_numbers_beside():
    rows, path = run(_cfg("mode=benchmark", "benchmark=paper_table", "benchmark.scenes=1", "benchmark.height=24",
                          "benchmark.width=32", "benchmark.gd_max_iters=3", "benchmark.reflectance=[ideal]",
                          "benchmark.models=[boom,epipolar_shadows]",
                          "benchmark.write=false"))
    assert path is None and len(rows) == 5  # 2 models x 2 optimisers, and mode=estimate's whole pipeline
    assert {r["optimiser"] for r in rows} == {"gd (paper)", "search + LM", "mode=estimate (whole pipeline)"}
    assert all(r["experiments"] == 6 for r in rows)
    assert rows[0]["paper_median"] == 0.0792  # Boom et al., true reflectance, as published
    assert all(0 <= r["median_error"] < 10 for r in rows)


def test_paper_table_resumes_from_its_rows_cache(tmp_path, monkeypatch):
    import benchmarks.paper_table as paper_table

    cache = tmp_path / "rows.jsonl"
    shrunk = ("mode=benchmark", "benchmark=paper_table", "benchmark.scenes=1", "benchmark.height=24",
              "benchmark.width=32", "benchmark.gd_max_iters=3", "benchmark.reflectance=[ideal]",
              "benchmark.models=[boom]", "benchmark.optimisers=[gd,search_lm]", "benchmark.write=false",
              f"benchmark.rows_cache={cache}")
    first, _ = run(_cfg(*shrunk))
    assert len(cache.read_text().splitlines()) == 2

    def not_again(*args):
        raise AssertionError("a cached row was measured again")

    monkeypatch.setattr(paper_table, "_gd", not_again)
    monkeypatch.setattr(paper_table, "_search_lm", not_again)
    assert run(_cfg(*shrunk))[0] == first
    # Other settings are other rows: measured, not taken from the file.
    with pytest.raises(InstantiationException, match="measured again"):
        run(_cfg(*shrunk, "benchmark.gd_max_iters=4"))
    cache.write_text("not json\n")
    with pytest.raises(InstantiationException, match="rows.jsonl:1 is not a row of the paper table"):
        run(_cfg(*shrunk))


def test_paper_table_names_an_unknown_row():
    # Hydra wraps the benchmark's ValueError; the message still names the row.
    with pytest.raises(InstantiationException, match="unknown reflectance \\['shiny'\\]"):
        run(_cfg("mode=benchmark", "benchmark=paper_table", "benchmark.reflectance=[shiny]", "benchmark.write=false"))


def test_unknown_mode_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown mode 'fly'"):
        run(_cfg("mode=fly"))


@pytest.mark.parametrize("mode, key", [("estimate", "estimate.input"), ("generate", "generate.out"),
                                       ("insert", "insert.scene")])
def test_a_required_setting_left_out_is_named_with_how_to_give_it(mode, key):
    with pytest.raises(ValueError, match=f"{key} is required: add {key}=<value>"):
        run(_cfg(f"mode={mode}"))
