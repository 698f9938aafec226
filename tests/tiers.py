"""The suite's named tiers (as warp names its suites in ``warp/tests/unittest_suites.py``), and
which tests must not share the machine's two cores with each other.

``scripts/test.sh --tier fast``: what a developer runs before each commit, at most 5 minutes
on 2 cores (two pytest-xdist workers). Every test that is neither marked ``slow`` nor named
in :data:`NOT_FAST` (tests of a few seconds and more that the full tier keeps); a new test
is in the fast tier unless it is marked slow or listed here. ``tests/conftest.py`` marks the
fast tier's tests ``fast`` (``pytest -m fast`` selects it).

``scripts/test.sh`` (``--tier full``): every test, what CI runs, at most 25 minutes on 2 cores.

``-m "not slow"`` still selects what it did (the marker is unchanged): the fast tier plus the
tests of :data:`NOT_FAST`. The measured times: docs/notes/suite.md.
"""
from __future__ import annotations

#: tier name -> what it is for (scripts/test.sh --help lists them)
TIERS = {
    "fast": "before each commit: the tests neither slow nor in tests/tiers.py's NOT_FAST "
            "(at most 5 minutes on 2 cores)",
    "full": "everything, what CI runs (at most 25 minutes on 2 cores)",
}

#: Tests not marked slow that the fast tier leaves to the full one: node id or its start (a
#: test and all its parameters, a file) -> the seconds it took (setup, call and teardown, on
#: one of two workers, the full suite on a 2-core machine shared with other test runs,
#: 2026-12-07; the same tests take about half of it on an idle machine). Every test of 6 s
#: and more there is listed, but the three smoke tests that run an app as a process (the
#: fast tier keeps them: test_fit_prints_where_everything_is 24 s, test_verify_exit_statuses
#: 29 s, test_a_fit_of_another_problem_is_refused_with_one_line 25 s). An entry that no
#: longer names a test is reported at collection (tests/conftest.py).
NOT_FAST: dict[str, str] = {
    "tests/experiments/test_command_line.py::test_a_misspelt_override_is_one_line_with_the_nearest_key": "11 s",
    "tests/experiments/test_command_line.py::test_help_on_every_user_command": "14 s",
    "tests/experiments/test_command_line.py::test_relative_paths_are_from_where_they_were_typed": "38 s",
    "tests/experiments/test_command_line.py::test_the_tensorboard_hint_quotes_a_path_with_spaces": "10 s",
    "tests/experiments/test_faults.py::test_a_disk_full_at_the_start_leaves_no_lock_and_the_next_run_proceeds": "73 s (2 cases)",
    "tests/experiments/test_faults.py::test_a_disk_full_partway_is_one_line_naming_the_file": "74 s (2 cases)",
    "tests/experiments/test_faults.py::test_a_full_disk_stops_the_run_in_one_line_and_the_resume_ends_where_it_would_have[84]": "45 s",
    "tests/experiments/test_faults.py::test_a_run_killed_at_a_seeded_random_point_resumes_to_the_same_result[0.659]": "39 s",
    "tests/experiments/test_fit_app.py::test_a_refused_resume_restores_hydra_files": "9 s",
    "tests/experiments/test_fit_app.py::test_a_sweep_with_a_failed_job_and_its_hparams_table": "17 s",
    "tests/experiments/test_fit_app.py::test_bad_input_of_each_kind_is_one_line_exit_2_and_nothing_written": "9 s",
    "tests/experiments/test_fit_app.py::test_continuation_through_the_app_runs_both_stages_and_says_where": "52 s",
    "tests/experiments/test_fit_app.py::test_init_starts_from_an_earlier_run_of_the_same_parameterisation": "15 s",
    "tests/experiments/test_run_dir_ownership.py::test_sigterm_ends_the_run_like_ctrl_c_and_it_resumes": "18 s",
    "tests/experiments/test_run_dir_ownership.py::test_two_runs_started_at_once_into_one_directory_one_runs_the_other_is_refused": "25 s",
    "tests/experiments/test_simulate.py::test_the_fit_keeps_its_mesh": "13 s",
    "tests/experiments/test_sweeps.py::test_optuna_ranks_an_invalid_trial_last": "14 s",
    "tests/linalg/backends/test_cudss.py::test_a_four_frame_nonlinear_fit_makes_one_analysis": "9 s",
    "tests/linalg/backends/test_pardiso.py::test_a_lower_thread_limit_than_the_analysis_had_does_not_crash_mkl": "14 s",
    "tests/linalg/test_threads.py::test_set_threads_keeps_mkl_dynamic_where_torch_alone_turns_it_off": "29 s",
    "tests/mesh/formats/test_convert.py::test_convert_sh_help": "11 s",
    "tests/mesh/formats/test_sniff.py::test_fbx_is_refused_by_the_fit_app": "12 s",
    "tests/physics/dynamics/test_explicit.py::test_a_stiff_trial_stops_at_its_budget_of_right_hand_sides": "23 s",
    "tests/physics/dynamics/test_explicit.py::test_an_accepted_trial_differentiates_beyond_the_budget_of_its_forward_pass": "11 s",
    "tests/physics/dynamics/test_explicit.py::test_dense_jacobian_is_one_augmented_solve_equal_to_the_columns_one_by_one": "13 s",
    "tests/physics/dynamics/test_explicit.py::test_torchdiffeq_derivatives_dopri5_tight_tolerance": "45 s",
    "tests/physics/dynamics/test_explicit.py::test_torchdiffeq_derivatives_rk4_and_the_sheet": "10 s",
    "tests/physics/dynamics/test_implicit.py::test_a_large_sag_is_found_by_load_increments": "8 s",
    "tests/physics/dynamics/test_implicit.py::test_error_estimate_by_step_halving_predicts_the_true_error": "19 s (2 cases)",
    "tests/physics/dynamics/test_make_integrator.py::test_jacobian_columns_equal_jvps_for_both_integrators": "14 s",
    "tests/physics/dynamics/test_make_integrator.py::test_step_shrinking_orders_and_the_same_trajectory_as_torchdiffeq": "15 s",
    "tests/problems/body/test_arm3d.py::test_arm_goes_through_the_user_animation_format": "20 s",
    "tests/problems/body/test_arm3d.py::test_neither_the_synthetic_target_nor_the_baseline_seeds_the_fit": "6 s",
    "tests/problems/body/test_arm3d.py::test_warm_start_setting_decides_where_newton_starts": "59 s (2 cases)",
    "tests/problems/body/test_dynamic_body.py::test_a_density_scale_among_the_parameters": "17 s",
    "tests/problems/body/test_init_field.py::test_a_layer_past_the_bounds_starts_clipped_into_them_and_says_so":
        "15 s (2 cases: the capsule tetrahedralised once)",
    "tests/problems/body/test_dynamic_body.py::test_dynamic_body_derivatives": "51 s (2 cases)",
    "tests/problems/body/test_dynamic_body.py::test_dynamic_flag_builds_the_body_in_time": "24 s",
    "tests/problems/body/test_dynamic_body.py::test_slow_motion_is_the_quasistatic_body": "13 s",
    "tests/problems/body/test_dynamic_body.py::test_under_gravity_the_body_starts_at_rest": "19 s",
    "tests/problems/body/test_dynamic_body.py::test_write_arm_adds_keyframed_jiggle": "11 s",
    "tests/problems/body/test_held_out.py::test_the_body_fits_the_other_frames_and_builds_its_validation_problem": "7 s",
    "tests/problems/body/test_motion.py::test_the_manifest_names_the_up_axis_of_a_body_without_a_rig": "8 s",
    "tests/problems/body/test_problem.py::test_capsule_fits_and_rerun_hits_the_tet_cache": "41 s (2 cases)",
    "tests/problems/body/test_problem.py::test_fit_app_runs_the_capsule_end_to_end": "12 s",
    "tests/problems/test_base.py::test_metric_names_are_the_metric_keys[arm3d]": "13 s",
    "tests/problems/test_base.py::test_problems_never_use_the_default_dtype": "8 s",
    "tests/problems/test_dynamic.py::test_dynamic_run_directory_pictures_and_tensorboard": "11 s",
    "tests/problems/test_dynamic.py::test_spring1d_dynamic_recovers_stiffness_and_damping[implicit]": "9 s",
    "tests/problems/test_dynamic.py::test_the_ode_dot_bound_catches_a_scaled_or_permuted_adjoint": "6 s",
    "tests/problems/test_dynamic.py::test_verify_app_on_the_dynamic_presets": "17 s",
    "tests/problems/test_input_checks.py::test_corrupt_arm_animation_cache_is_rebuilt": "31 s",
    "tests/problems/test_membrane2d.py::test_canonical_sizes_and_truth": "20 s",
    "tests/problems/test_membrane2d.py::test_difference_preconditioner_same_damped_step_in_fewer_cgls_iterations": "7 s",
    "tests/reporting/test_body.py::test_every_modulus_that_leaves_the_tool_says_its_unit[relative]": "7 s",
    "tests/reporting/test_body.py::test_the_body_outputs_read_the_runs_evaluations": "12 s",
    "tests/reporting/test_body.py::test_the_error_plot_of_a_fit_holds_its_validation_frames": "16 s",
    "tests/reporting/test_results.py::test_outputs_are_byte_identical_across_directories_and_processes": "6 s",
    "tests/run/test_checkpoint.py::test_killed_run_resumes_exactly": "37 s (3 cases)",
    "tests/run/test_continuation.py::test_auto_splits_a_synthetic_body_only_where_a_frame_is_near_a_fold": "9 s",
    "tests/run/test_continuation.py::test_frames_near_a_fold_and_the_two_stages": "34 s",
    "tests/run/test_continuation.py::test_no_frame_near_a_fold_is_one_run": "10 s",
    "tests/run/test_continuation.py::test_with_frames_keeps_the_targets_noise_included": "19 s",
    "tests/run/test_resume_warm_start.py::test_a_body_with_validation_frames_resumes_exactly": "6 s",
    "tests/run/test_resume_warm_start.py::test_the_checkpoint_holds_the_warm_start_anchor": "8 s",
    "tests/run/test_resume_warm_start.py::test_warm_started_arm_resumes_exactly": "10 s",
    "tests/scripts/bench/test_factorization.py::test_factorization_layout": "12 s",
    "tests/scripts/bench/test_membrane2d.py::test_membrane2d_benchmark_layout": "17 s",
    "tests/solvers/split_bregman/test_resume.py::test_resume_noise_free_fixed_weight_is_bit_identical": "6 s",
}

#: Node id starts -> xdist group (``--dist loadgroup``): each group's tests run on one
#: worker, one after another. Tests that start more processes than the worker's one core
#: (torchrun's ranks) would slow each other and the other worker's tests; modules whose
#: module-scoped fixture is expensive (a fitted capsule, an uninterrupted reference run)
#: build it once rather than on both workers.
GROUPS: dict[str, str] = {
    "tests/run/distributed/": "torchrun",
    "tests/experiments/test_faults.py": "faults",
    "tests/experiments/test_simulate.py": "simulate",
}


def matches(nodeid: str, start: str) -> bool:
    """Whether ``nodeid`` is the test (or file, or folder) that ``start`` names."""
    return nodeid == start or nodeid.startswith(start if start.endswith("/") else
                                                (start + "::", start + "["))


def in_fast_tier(nodeid: str, slow: bool) -> bool:
    return not slow and not any(matches(nodeid, start) for start in NOT_FAST)


def group_of(nodeid: str) -> str | None:
    return next((name for start, name in GROUPS.items() if matches(nodeid, start)), None)
