import json

import torch

from benchmarks import common


def test_cpu_results_carry_the_machine_reference(tmp_path, monkeypatch):
    monkeypatch.setattr(common, "RESULTS", tmp_path)
    threads = torch.get_num_threads()
    md = common.write_results("probe", torch.device("cpu"), [{"a": 1}], "header", ["a"])
    assert torch.get_num_threads() == threads  # the reference's one-thread pass restores the threads
    reference = json.loads(md.with_suffix(".json").read_text())["meta"]["machine_reference"]
    assert 0 < reference["elementwise_ns"] < 100 and reference["matmul_gflops"] > 0
    assert reference["threads"] == threads
    text = md.read_text()
    assert f"{reference['elementwise_ns']} ns per element" in text and "| 1 |" in text
