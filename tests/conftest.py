"""Shared test set-up: the repo root on sys.path; `gpu` tests skipped where no CUDA device exists."""
import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _cuda_available() -> bool:
    try:
        from pbf_cuda import available_backends
        return "cuda" in available_backends()
    except Exception:
        return False


# The longest tests go first: with pytest-xdist (scripts/test.sh runs one worker per core) a worker that
# starts the smoke demo last would finish minutes after the others.
LONGEST_FIRST = ("test_harness_demo.py", "test_atmosphere_energy.py")


# Slow tests, marked here by name (besides @pytest.mark.slow in their files): each took 5 s or more on one
# core in a run of the whole suite with --durations=0 (one worker per core, a 16-core x86-64 host,
# 2026-11-28). `scripts/test.sh --quick` (-m "not slow") leaves them out; the whole suite runs them.
# Seconds are the slowest parametrization's.
SLOW = {
    "test_atmosphere_energy.py": (
        "test_linear_gravity_wave_keeps_its_energy_and_frequency_over_two_periods",       # 109
        "test_steep_gravity_wave_loses_energy_at_first_order_in_dt_and_never_gains",      # 108
        "test_inviscid_cellular_flow_never_gains_kinetic_energy",                         # 52
        "test_heated_closed_box_keeps_its_mass_in_place_and_closes_its_heat_budget",      # 31
        "test_inviscid_shear_wave_and_taylor_green_vortex_never_gain_energy",             # 24
        "test_shear_wave_decays_at_the_rate_its_viscosity_implies",                       # 20
        "test_lattice_with_random_velocities_never_gains_kinetic_energy",                 # 10
        "test_heated_ground_layer_stays_on_the_floor",                                    # 10
        "test_smoothing_and_water_budget_of_a_cloudy_run",                                # 7
    ),
    "test_cloud_physics.py": (
        "test_column_heat_input_does_not_depend_on_resolution",                           # 44
        "test_internal_gravity_wave_frequency",                                           # 27
        "test_parcel_condenses_at_the_lifting_condensation_level",                        # 10
        "test_total_water_is_conserved_over_a_long_run",                                  # 10
    ),
    "test_environment.py": ("test_gravity_wave_in_an_inversion_layer_has_that_layers_buoyancy_frequency",),  # 36
    "test_adaptive.py": (
        "test_heated_criterion_refines_the_column_above_the_heated_patch",                # 33
        "test_adaptive_run_keeps_mass_exact_and_refines_clouds",                          # 9
    ),
    "test_solver_core.py": (
        "test_density_next_to_walls_is_the_brute_force_sum",                              # 30
        "test_neighbour_lists_give_the_cell_search_results",                              # 7
    ),
    "test_constraint_bruteforce.py": (
        "test_density_lambda_and_position_correction",                                    # 17
        "test_velocity_projection_is_the_conjugate_gradients_of_J",                       # 10
        "test_adjoint_identity_and_energy_of_the_converged_projection",                   # 7
    ),
    "test_report.py": (
        "test_cycling_renders_are_one_side_by_side_figure_with_missing_cells_marked",     # 28
        "test_shallow_cumulus_section_sets_the_grid_beside_the_particles_of_the_same_seeds",  # 20
        "test_compare_section_draws_the_full_domain_convergence_when_its_csv_is_there",   # 19
        "test_first_screen_is_verdict_cards_from_the_data",                               # 11
        "test_header_names_every_device_commit_and_scale_of_the_sections",                # 9
        "test_a_time_to_solution_card_appears_when_its_data_exists",                      # 8
        "test_report_partial_inputs_and_unavailable_render",                              # 8
    ),
    "test_adaptive_pareto.py": (
        "test_the_interval_holds_the_speedup_widens_with_noise_and_narrows_with_seeds",   # 20
        "test_analysis_writes_a_verdict_with_cost_ratio_and_speedup",                     # 7
        "test_analysis_leaves_out_a_variant_that_blew_up_in_two_seeds",                   # 6
    ),
    # The grid baseline's tests (jax compiles each new shape): measured on the 2-core machine with other jobs
    # sharing its cores, one process (seconds inflated 2-3x); marked where they took 15 s or more.
    "test_grid_simulation.py": (
        "test_instability_is_reported",                                                   # 128
        "test_seed_moves_the_heating_pattern",                                            # 33
        "test_phase_timing_mode_gives_the_same_state",                                    # 24
    ),
    "test_grid_physics.py": (
        "test_total_water_conserved_with_heating_and_condensation",                       # 82
        "test_uniform_vapor_cloud_layer_base_at_lcl",                                     # 55
        "test_stratified_wave_frequency",                                                 # 37
        "test_resting_stratified_atmosphere_stays_at_rest",                               # 33
        "test_parcel_scene_rising_air_condenses_at_its_lcl",                              # 26
        "test_phase_transition_matches_ode_and_conserves",                                # 22
    ),
    "test_grid_projection.py": (
        "test_poisson_solve_matches_dense_matrix",                                        # 74
        "test_divergence_after_projection",                                               # 35
        "test_gradient_is_removed_and_solenoidal_field_kept",                             # 26
    ),
    "test_grid_bench.py": ("test_writes_then_appends_rows",),                             # 75
    "test_grid_compat.py": ("test_van_leer_with_a_wall_runs_and_conserves",),             # 32
    "test_grid_noise.py": ("test_heating_pattern_matches_reference",),                    # 18
    "test_export.py": ("test_cli_export_grid_run_netcdf",),                               # 64
    "test_cycling.py": ("test_grid_heating_follows_the_time_of_day",),                    # 25
    "test_cbl.py": ("test_mixed_layer_follows_encroachment",),                            # 39
}


def pytest_collection_modifyitems(config, items):
    slow = pytest.mark.slow
    for item in items:
        if getattr(item, "originalname", item.name) in SLOW.get(item.path.name, ()):
            item.add_marker(slow)
    items.sort(key=lambda item: next((i for i, name in enumerate(LONGEST_FIRST) if item.nodeid.startswith(f"tests/{name}")),
                                     len(LONGEST_FIRST)))
    if _cuda_available():
        return
    skip = pytest.mark.skip(reason="no CUDA device (gpu tests run on the device machine)")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)
