"""Run the attack matrix (issue 29: an attacker's and a careless user's moves against the rig) and
write its table into docs/reliability.md.

    .venv/bin/python bench/attack_matrix.py [--out docs/reliability.md] [--no-write]

Each row is one attack and the test that mounts it for real - on the simulated cage, through real
processes, files, signals, accounts (`setpriv`), PID namespaces (`unshare`), a real PostgreSQL and a
real browser - and asserts the outcome the row states. The table records, for this machine and
this run, whether the outcome held and how long the test took. The same tests run in CI with the
suite; this script only regenerates the figures (the way bench/fault_matrix.py does for faults).
"""

from __future__ import annotations

import argparse
import datetime as dt
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import NamedTuple

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "reliability.md"
MARK = "<!-- attacks -->"


class Attack(NamedTuple):
    attack: str
    outcome: str
    test: str  # pytest node id (file::name, a parametrized test runs all its cases)


ATTACKS = [
    Attack("a coil supply named as a load", "`rig check` and `rig run` refuse it, exit 2, before any output is on",
           "tests/engine/test_output_limits.py::test_rig_check_refuses_a_cage_device_as_a_load"),
    Attack("the same, forced past the check", "the coil's own limits refuse the set-point; coil peak 2.434 A against the 2.5 A limit, run `error`",
           "tests/engine/test_output_limits.py::test_forced_past_the_check_the_coil_is_held_by_the_cage_limits"),
    Attack("rig configuration edited during a run, then the rig SIGKILLed", "the guardian acts on its frozen copy: outputs off within 1 s",
           "tests/engine/test_guardian_pair.py::test_config_edited_then_sigkill_outputs_off_within_1_s"),
    Attack("configuration edited, then the rig SIGSTOPped", "the guardian kills the rig and switches off (3 s heartbeat bound)",
           "tests/engine/test_guardian_pair.py::test_config_edited_then_sigstop_the_guardian_kills_and_switches_off"),
    Attack("the guardian SIGKILLed during a run", "a fault: outputs off and the run `error` within 1 s",
           "tests/engine/test_guardian_pair.py::test_guardian_sigkilled_the_run_goes_safe_and_ends_error_within_1_s"),
    Attack("the guardian SIGSTOPped", "a fault, as a dead guardian",
           "tests/engine/test_guardian_pair.py::test_guardian_stopped_is_a_fault_too"),
    Attack("links planted in a run folder (run.h5, report.txt, csv/)", "exports and reports replace the link, never write its target",
           "tests/store/test_run_folder_files.py::test_export_and_report_replace_planted_links_never_their_targets"),
    Attack("a linked run.sqlite or run folder", "`rig show`/`verify`/`export`/`report`: one line, exit 2",
           "tests/store/test_run_folder_files.py::test_a_linked_run_sqlite_or_run_folder_is_one_line"),
    Attack("x.png -> /etc/shadow served by the page", "refused; nothing outside the folder is read",
           "tests/web/test_page_threats.py::test_links_in_run_folders_are_not_followed"),
    Attack("another account's lock folder with planted links", "refused, one line; nothing outside the folder is written",
           "tests/engine/test_lock_folder.py::test_another_users_folder_with_a_planted_link_is_refused_and_nothing_is_written"),
    Attack("a second account on a private lock folder", "one line naming the folder's owner and the fix, exit 2",
           "tests/engine/test_lock_folder.py::test_second_user_on_a_private_folder_gets_one_line"),
    Attack("`localhost` and `127.0.0.1` for the same supplies", "one lock: the second command is refused",
           "tests/engine/test_lock_folder.py::test_localhost_and_127_0_0_1_take_the_same_lock"),
    Attack("another local account opens the page", "401 without the owner's token; the access file is unreadable to it",
           "tests/web/test_page_threats.py::test_another_account_neither_sees_nor_operates_the_page"),
    Attack("another account answers the prompt or aborts through the page or control/", "refused or ignored (recorded once); the owner's abort works",
           "tests/web/test_page_threats.py::test_another_account_cannot_answer_or_abort_a_live_run"),
    Attack("a page of another loopback origin frames the run page", "the browser shows nothing (CSP frame-ancestors, X-Frame-Options)",
           "tests/web/test_page_threats.py::test_a_page_of_another_origin_cannot_frame_the_run_page"),
    Attack("a 200 MB POST", "413 before the body is read; server memory unchanged",
           "tests/web/test_page_threats.py::test_a_200_mb_post_is_refused_before_it_is_read"),
    Attack("`Infinity`, `NaN`, huge numbers in an answer", "400 with one line",
           "tests/web/test_page_threats.py::test_bad_numbers_in_an_answer_are_a_400_of_one_line"),
    Attack("run ids with ?, # or %, serials with /", "links work (quoted path segments)",
           "tests/web/test_page_threats.py::test_odd_run_ids_link_correctly_in_the_browser"),
    Attack("`rig runs` from another PID namespace during a live run", "the run stays `running`, no seal written",
           "tests/store/test_run_lease.py::test_a_reader_in_another_pid_namespace_leaves_a_live_run_running"),
    Attack("verdict changed in an unsynced run's results, then `rig lab sync`", "refused, one line, listed in the audit; the other runs sync",
           "tests/lab/test_lab_safety.py::test_a_run_changed_after_its_seal_is_refused_and_audited"),
    Attack("report.html edited (PASS to FAIL)", "`rig verify`: reports CHANGED, data intact",
           "tests/store/test_run_folder_files.py::test_an_edited_report_is_a_changed_report_not_changed_data"),
    Attack("files and tables added or deleted in a run folder", "`rig verify` lists each",
           "tests/store/test_run_folder_files.py::test_deleted_and_added_files_and_tables"),
    Attack("a NUL byte in a serial or name", "refused at the procedure/configuration with file and line, exit 2",
           "tests/engine/test_text_rule.py::test_control_characters_are_refused_with_file_and_line"),
    Attack("an old run with a NUL byte in the lab sync", "that run skipped with one line; the others sync",
           "tests/lab/test_lab_safety.py::test_one_run_the_index_cannot_store_never_stops_the_others"),
    Attack("a 300-character serial", "one line, exit 2",
           "tests/engine/test_text_rule.py::test_a_300_character_serial_is_refused_in_one_line_exit_2"),
    Attack("a truncated run.sqlite", "listed `damaged`; the other runs listed; one line for show/verify",
           "tests/store/test_run_folder_files.py::test_a_damaged_run_is_listed_and_never_hides_the_others"),
    Attack("the lab index table locked at run close", "`rig run` exits within the 5 s bound",
           "tests/lab/test_lab_safety.py::test_a_locked_index_table_holds_a_closing_run_at_most_the_bound"),
    Attack("`[lab] url` with a percent-encoded password key", "refused, one line",
           "tests/lab/test_lab_safety.py::test_a_percent_encoded_password_key_is_refused"),
    # issue 51: safety, third round
    Attack("coil_x's supply declared again as `[devices.aux]` (through localhost) and driven as a load", "`rig check`, `rig run` and the interlock refuse the configuration, exit 2, nothing written",
           "tests/engine/test_wire_keyed_limits.py::test_rig_run_refuses_it_before_the_lock_or_any_write"),
    Attack("the same, past every refusal", "the second name has coil_x's cage limits (2.5 A, 12 V), keyed by the wire address",
           "tests/engine/test_wire_keyed_limits.py::test_a_second_name_has_the_coils_limits"),
    Attack("a set-point `rig check` refuses (110 uT on z: 2.68 A of 2.5 A)", "`rig run` refuses it by the same check before the lock or any output",
           "tests/engine/test_wire_keyed_limits.py::test_rig_run_refuses_what_rig_check_refuses"),
    Attack("-95 uT on z of an uncharacterized cage (142 uT true)", "`rig check` LIMIT with the lab field counted until measured",
           "tests/engine/test_field_limit_measured.py::test_the_unmeasured_lab_field_counts_against_the_field_limit"),
    Attack("the same, forced past the check", "the reference's reading beyond 120 uT ends the run `error`, outputs off; true |B| beyond 120 uT for 0.09 s",
           "tests/engine/test_field_limit_measured.py::test_forced_past_the_check_the_measured_field_takes_the_outputs_safe"),
    Attack("a sine across the cancelled lab field (relay flips)", "`rig check` LIMIT and `rig run` refuses it",
           "tests/test_check_sine_polarity.py::test_a_sine_across_the_cancelled_lab_field_is_a_limit"),
    Attack("0.5 A set-point steps into the coils' 25 ms L/R (22 A/s against 10 A/s)", "with `coil_tau_s` the true coil current peaks within 10 A/s",
           "tests/cage/test_coil_slew.py::test_on_the_simulated_cage_the_true_coil_current_keeps_the_slew"),
    Attack("rig and guardian both SIGKILLed, coils and a load left on", "the next `rig runs` switches them off and reads them back",
           "tests/engine/test_runs_after_both_killed.py::test_rig_runs_switches_off_what_a_dead_run_left_on"),
    Attack("heater and coil left on, then `rig run smoke`", "found on, switched off before the first step; the end line is read back",
           "tests/engine/test_outputs_found_on.py::test_outputs_found_on_are_switched_off_before_the_first_step"),
    Attack("`rig safe` with a nan field limit, a heater limit of -1, a 2-element max_current_a", "every output switched off and read back",
           "tests/engine/test_safe_addresses.py::test_one_bad_key_elsewhere_does_not_stop_rig_safe"),
    Attack("`rig safe` with a TOML typo or a 5000-deep array", "the last run's copy of the file: every output off, said in one line",
           "tests/engine/test_safe_addresses.py::test_an_unparsable_file_is_replaced_by_the_last_runs_copy"),
    Attack("a 6 A heater at 30 V compliance (144 W, DUT to 313 C)", "`rig check` one LIMIT line per problem (power, temperature), exit 1",
           "tests/engine/test_heat_limits.py::test_rig_check_refuses_the_issues_heater_with_one_limit_line_per_problem"),
    Attack("the same heater through `rig run`", "refused before any output is written",
           "tests/engine/test_heat_limits.py::test_rig_run_refuses_the_heater_before_any_output_is_written"),
    Attack("the DUT warmed past its max_temperature_c", "the run `error`, heater off within 1 s (0.22-0.23 s measured)",
           "tests/engine/test_heat_limits.py::test_the_dut_over_its_limit_is_taken_safe_within_a_second_on_the_simulated_cage"),
    Attack("recorder and guardian SIGSTOPped while a reader seals the run, then SIGCONT", "the run ends `error`, outputs off in 0.16 s, the reader's status and seal kept",
           "tests/engine/test_sealed_by_reader.py::test_a_run_sealed_by_a_reader_while_stopped_ends_error_outputs_off_seal_kept"),
    Attack("the same, only the guardian resumed", "the guardian kills the stopped rig and switches off",
           "tests/engine/test_sealed_by_reader.py::test_the_guardian_alone_acts_on_the_reader_seal_and_kills_a_rig_still_stopped"),
    Attack("forged runs (made from nothing, edited and re-sealed) in a runs folder another account can write", "`rig lab sync` refuses the folder or skips the runs, one line each",
           "tests/lab/test_lab_forged_runs.py::test_forged_runs_from_another_account_never_reach_the_index"),
    Attack("an unsealed run", "skipped by `rig lab sync` with a line; listed in the audit",
           "tests/lab/test_lab_forged_runs.py::test_an_unsealed_run_of_the_rig_s_own_is_skipped_with_a_line"),
    Attack("a value of 1e308 in a run, and one already in the index", "the run refused; `rig lab audit` and trend survive, limits unmoved",
           "tests/lab/test_lab_forged_runs.py::test_audit_and_trend_survive_an_extreme_value_an_older_sync_stored"),
    Attack("links (dangling too) planted at `rig calibrate --out/--c-header/--px4/--history`, `example-data`, `design --out`", "refused in one line, the target untouched and never created",
           "tests/test_output_no_follow.py::test_a_planted_link_is_refused_and_its_target_left_alone"),
    Attack("register maps with scale 0/NaN/-1, i_max inf, addresses -1/70000/2^40", "refused in one line naming file, line, register and fix",
           "tests/drivers/test_regmap_parser.py::test_hostile_values_are_refused_with_file_line_register_and_fix"),
    Attack("a 30000-register map (`rig safe` busy > 300 s)", "refused at the cap (4096) in the time tomllib takes; parsing linear",
           "tests/drivers/test_regmap_parser.py::test_a_map_of_more_than_max_registers_is_refused_and_one_at_the_cap_is_read"),
    Attack("a CSV cell of 1e308", "one line naming its line and column, exit 2",
           "tests/test_hostile_numbers.py::test_a_huge_csv_cell_names_its_line_and_column"),
    Attack("a singular nominal coil matrix; NaN and unknown keys in the simulator configuration", "one line each, exit 2",
           "tests/test_hostile_numbers.py::test_a_singular_nominal_coil_matrix_is_refused_at_load"),
    Attack("right-to-left override and zero-width characters in a step name or serial", "refused with the character's name",
           "tests/engine/test_text_rule.py::test_every_bidi_control_and_zero_width_character_is_refused_in_a_label"),
    Attack("a perming step killed with the DUT's automatic set/reset off", "the next opening of the sensor turns it on",
           "tests/test_perming.py::test_a_killed_perming_step_leaves_set_reset_off_and_the_next_opening_turns_it_on"),
]  # fmt: skip


def run(attacks: list[Attack]) -> dict[str, tuple[str, float]]:
    """Run every attack's test; node id -> (outcome, seconds) from pytest's JUnit XML."""
    xml = Path(tempfile.mkdtemp(prefix="attacks-")) / "junit.xml"
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={xml}",
           *[a.test for a in attacks]]  # fmt: skip
    subprocess.run(cmd, cwd=ROOT, check=False)
    out: dict[str, tuple[str, float]] = {}
    for case in ET.parse(xml).getroot().iter("testcase"):
        path = case.get("classname", "").replace(".", "/") + ".py"
        name = case.get("name", "").split("[")[0]
        outcome = "held"
        if case.find("failure") is not None or case.find("error") is not None:
            outcome = "**BROKEN**"
        elif case.find("skipped") is not None:
            outcome = "skipped"
        key = f"{path}::{name}"
        old, took = out.get(key, ("held", 0.0))
        worst = outcome if outcome != "held" else old
        out[key] = (worst, took + float(case.get("time", 0.0)))
    return out


def table(attacks: list[Attack], results: dict[str, tuple[str, float]]) -> str:
    rows = ["| attack | expected outcome | outcome | test (time) |", "|---|---|---|---|"]
    for a in attacks:
        outcome, took = results.get(a.test, ("**not run**", 0.0))
        rows.append(
            f"| {a.attack} | {a.outcome} | {outcome} | `{a.test.split('::')[1]}` ({took:.1f} s) |"
        )
    return "\n".join(rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--out", type=Path, default=DOC, help="document to update (default: %(default)s)"
    )
    ap.add_argument("--no-write", action="store_true", help="print the table only")
    args = ap.parse_args()
    t0 = time.monotonic()
    results = run(ATTACKS)
    when = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    held = sum(results.get(a.test, ("",))[0] == "held" for a in ATTACKS)
    section = (f"{MARK}\nLast run {when}, {time.monotonic() - t0:.0f} s; {held} of {len(ATTACKS)}"
               f" attacks held.\n\n{table(ATTACKS, results)}\n{MARK}")  # fmt: skip
    print(section)
    if not args.no_write:
        text = args.out.read_text(encoding="utf-8")
        if MARK not in text:
            print(f"{args.out} has no {MARK} section", file=sys.stderr)
            return 2
        head, _, rest = text.partition(MARK)
        _, _, tail = rest.partition(MARK)
        args.out.write_text(head + section + tail, encoding="utf-8")
        print(f"wrote {args.out}")
    return 0 if held == len(ATTACKS) else 1


if __name__ == "__main__":
    raise SystemExit(main())
