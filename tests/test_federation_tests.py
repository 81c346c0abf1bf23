"""make test's two workers: the tests that start federations are told apart per test, so a
module's in-process tests are spread while its federations run one after another."""

from __future__ import annotations

from pathlib import Path

import pytest
from federation_tests import runs_alongside, starts_federations

TESTS = Path(__file__).parent


@pytest.mark.parametrize(
    "nodeid",
    [
        "test_placement.py::test_a_host_whose_seed_makes_another_variant_is_refused_in_one_line",
        "test_experiments.py::test_tiny_multirun_then_plot",  # fedhpg-run -m through procs.start
        "test_cuda_untouched.py::test_a_distributed_api_run_never_asks_cuda",  # code in a string
        "test_cuda_untouched.py::test_fedhpg_run_on_the_cpu_never_asks_cuda[demo]",  # a script
        "test_api.py::test_a_loaded_policy_reproduces_a_distributed_runs_summary",
        "test_connection_guard.py::test_a_failing_event_handler_does_not_stall_the_socket",  # fork
        "test_counted_clock.py::test_emulated_times_identical_across_runs_and_under_load",  # hog
        # a long-tier run of fedhpg-run in a module that otherwise runs console scripts quickly
        "test_cli_output.py::test_the_first_cartpole_run_says_it_compiles_before_the_server_waits",
    ],
)
def test_a_test_that_starts_processes_runs_with_the_federations(nodeid: str) -> None:
    module = nodeid.split("::", 1)[0]
    assert starts_federations(TESTS / module, f"tests/{nodeid}")


def test_a_module_that_cannot_be_read_fails_the_run_rather_than_being_spread() -> None:
    with pytest.raises(OSError):
        starts_federations(TESTS / "test_no_such_module.py", "tests/test_no_such_module.py::a")


@pytest.mark.parametrize(
    "nodeid",
    [
        "test_experiments.py::test_every_preset_composes_and_validates[fig1_batch_size]",
        "test_experiments.py::test_bad_overrides_name_the_key[algo=nope-algo-allowed: fedhpg]",
        "test_tolerance.py::test_warn_runs_an_intolerant_rule_and_says_so",
        "test_codec.py::anything",  # a module that starts no process anywhere
        "test_cli_output.py::test_the_demo_says_it_sleeps_and_a_preset_says_what_it_changed",
        "test_security.py::test_keys_command_writes_pairs_and_the_allow_list",  # BIN / fedhpg-keys
    ],
)
def test_an_in_process_test_is_spread(nodeid: str) -> None:
    module = nodeid.split("::", 1)[0]
    assert not starts_federations(TESTS / module, f"tests/{nodeid}")


def test_a_helper_or_fixture_that_starts_processes_or_a_shared_fixture_makes_a_federation_test(
    tmp_path: Path,
) -> None:
    module = tmp_path / "test_sample.py"
    module.write_text(
        "import pytest\n"
        "from procs import processes, start\n"
        "RUN = ['rounds=1']\n"
        "def _federation():\n    with processes() as started:\n        start(started, 'x', RUN)\n"
        "@pytest.fixture\ndef served():\n    _federation()\n"
        "def test_by_helper():\n    _federation()\n"
        "def test_by_fixture(served):\n    pass\n"
        "def test_by_constant_only():\n    assert RUN\n"
        "class TestGroup:\n    def test_method(self):\n        _federation()\n"
        "@pytest.fixture(scope='module')\ndef built_once():\n    return 1\n"
        "@pytest.fixture\ndef per_test(built_once):\n    return built_once\n"
        "def test_by_shared_fixture(per_test):\n    assert per_test\n",
        encoding="utf-8",
    )
    verdicts = {
        name: starts_federations(module, f"tests/test_sample.py::{name}")
        for name in ("test_by_helper", "test_by_fixture", "test_by_constant_only",
                     "TestGroup::test_method", "test_by_shared_fixture")
    }  # fmt: skip
    assert verdicts == {
        "test_by_helper": True,
        "test_by_fixture": True,
        "test_by_constant_only": False,
        "TestGroup::test_method": True,
        "test_by_shared_fixture": True,
    }


def test_the_docs_pages_run_alongside_the_federations_one_page_a_unit() -> None:
    """The long tier's docs pages start federations, but may run beside the serial unit; the
    other tests of the module, and the federations elsewhere, may not."""
    for pages in (
        "tests/test_docs.py::test_the_pages_code_runs_as_printed[README.md]",
        "tests/test_docs.py::test_the_pages_code_runs_as_printed[environments.md:14]",  # a block
    ):
        assert starts_federations(TESTS / "test_docs.py", pages)
        assert runs_alongside(TESTS / "test_docs.py", pages)
    for nodeid in (
        "tests/test_docs.py::test_the_readmes_quickstart_output_is_what_the_demo_prints",
        "tests/test_resources.py::test_resource_attacks_leave_the_run_intact",
        "tests/test_hosts.py::test_theta_does_not_depend_on_the_placement_of_the_agents[fedhpg]",
    ):
        assert not runs_alongside(TESTS / nodeid.split("::")[0].removeprefix("tests/"), nodeid)


def test_a_fast_run_checked_only_by_its_outputs_may_run_alongside_too() -> None:
    """make test's fedhpg-run runs on a free port with the defaults' waits, marked alongside,
    leave the serial unit; an unmarked test of the same module stays in it."""
    marked = "tests/test_experiments.py::test_tiny_multirun_then_plot"
    assert starts_federations(TESTS / "test_experiments.py", marked)
    assert runs_alongside(TESTS / "test_experiments.py", marked)
    other = (
        "tests/test_experiments.py::test_fedhpg_run_rejects_an_unknown_group_option_with_one_line"
    )
    assert starts_federations(TESTS / "test_experiments.py", other)
    assert not runs_alongside(TESTS / "test_experiments.py", other)
