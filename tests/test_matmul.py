"""bfloat16 products on a CPU that only emulates them: told from /proc/cpuinfo, and warned of in the job's log."""
import pytest

from dswm import settings as runconfig
from dswm.config import load_yaml
from dswm.methods.matmul import emulated_bfloat16_warning, native_bfloat16
from dswm.pipeline.setup import warn_emulated_bfloat16

from conftest import ROOT

XEON = "processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512bw avx512_vnni\n\nprocessor\t: 1\nflags\t\t: fpu avx512f\n"
SAPPHIRE = XEON.replace("avx512_vnni", "avx512_vnni avx512_bf16 amx_tile amx_bf16")
GRAVITON = "processor\t: 0\nFeatures\t: fp asimd sve bf16 i8mm\nCPU implementer\t: 0x41\n"
ARM_OLD = "processor\t: 0\nFeatures\t: fp asimd evtstrm aes\n"


@pytest.mark.parametrize("text, native", [(XEON, False), (SAPPHIRE, True), (GRAVITON, True), (ARM_OLD, False),
                                          ("processor\t: 0\nmodel name\t: unknown\n", None)])
def test_native_bfloat16_is_read_from_the_cpu_flags(tmp_path, text, native):
    path = tmp_path / "cpuinfo"
    path.write_text(text)
    assert native_bfloat16(path) is native
    # a flag that only contains the name is not the flag
    path.write_text(text.replace("bf16", "bf16x"))
    assert native_bfloat16(path) is (None if native is None else False)


def test_native_bfloat16_is_unknown_without_cpuinfo(tmp_path):
    assert native_bfloat16(tmp_path / "absent") is None


def test_the_warning_names_the_setting_only_for_emulated_bfloat16_on_a_cpu():
    key = "methods.sac.matmul_dtype"
    message = emulated_bfloat16_warning(key, "bfloat16", "cpu", native=False)
    assert message is not None and message.startswith(key + ": bfloat16") and f"set {key}: float32" in message
    assert emulated_bfloat16_warning(key, "bfloat16", "cpu", native=True) is None
    assert emulated_bfloat16_warning(key, "bfloat16", "cuda:0", native=False) is None
    assert emulated_bfloat16_warning(key, "float32", "cpu", native=False) is None
    assert emulated_bfloat16_warning(key, None, "cpu", native=False) is None


def test_a_job_of_a_bfloat16_method_prints_the_warning_to_its_log(capsys):
    s = runconfig.resolve({**load_yaml(ROOT / "config.yaml"), "profile": "paper"})
    assert s.methods["sac"].options.matmul_dtype == "bfloat16"   # the paper profile's SAC: bfloat16 products
    demo = runconfig.resolve(load_yaml(ROOT / "config.yaml"))   # the demo's: float32, which warns of nothing
    assert warn_emulated_bfloat16(demo.methods["sac"], "cpu", native=False) is None
    assert warn_emulated_bfloat16(demo.methods["maddpg"], "cpu", native=False) is None
    assert warn_emulated_bfloat16(s.methods["sac"], "cpu", native=False).startswith("methods.sac.matmul_dtype:")
    assert capsys.readouterr().err.startswith("WARNING: methods.sac.matmul_dtype: bfloat16 products")
    assert warn_emulated_bfloat16(s.methods["sac"], "cpu", native=True) is None
    assert warn_emulated_bfloat16(s.methods["ppo"], "cpu", native=False) is None   # no such setting
    assert capsys.readouterr().err == ""
