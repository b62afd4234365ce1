import jax

# Numerical tests run in float64; float32 tests ask for float32 arrays explicitly.
jax.config.update("jax_enable_x64", True)


import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _fresh_compilation_caches():
    """Drop JAX's compiled programs after each test module: the suite compiles several
    hundred XLA programs, and a long-lived process that keeps them all has crashed inside
    XLA's compiler (not reproducible in a fresh process)."""
    yield
    jax.clear_caches()


# The heavy cases of the default suite's checks, run with `pytest -m extended` (CI runs
# them in a second command, after the default suite): each took ≥ 8 s on one worker of the
# 2-core reference machine (`pytest --durations`, idle; mostly compiling SE(3),
# composition and coupled-body programs), so that the default suite stays near 10 minutes.
# Whatever they cost, the default suite keeps the paper's equivalence theorem, the Poisson
# property, the gradient and implicit-derivative checks against finite differences, one
# fast-against-reference parity case, the float32 batches and the two-process run.
EXTENDED = frozenset(
    {
        "tests/test_site_neighbors.py::test_batch_of_systems_with_their_own_lists",  # 11 s
        # The order-5 and order-8 Lie-group Runge–Kutta methods: the tableau-driven step they
        # share with RKMK4 runs by default (RKMK4's tests, the step-bound test, RKMK8 on the
        # group); their own orders and parity under -m extended.
        "tests/test_kernel_parity.py::test_iterates_and_gradients_equal_reference[rkmk8-heavy-top]",  # 38 s
        "tests/test_kernel_parity.py::test_batch_equals_reference[rkmk8-heavy-top]",  # 14 s
        "tests/test_kernel_parity.py::test_iterates_and_gradients_equal_reference[rkmk5]",  # 13 s
        "tests/test_rkmk.py::test_order_of_the_tableau[rkmk8]",  # 15 s
        "tests/test_batch.py::test_failures_are_per_body[exp]",  # 11 s
        "tests/test_batch.py::test_fast_equals_generic[dep-exp]",  # 8 s
        "tests/test_batch.py::test_fast_path_gradient_finite_when_a_body_fails",  # 12 s
        "tests/test_batch.py::test_sharded_equals_unsharded",  # 13 s
        "tests/test_branch_rule.py::test_successful_steps_are_on_the_continued_branch[dep-exp]",  # 18 s
        "tests/test_branch_rule.py::test_successful_steps_are_on_the_continued_branch[moser-veselov]",  # 16 s
        "tests/test_contracts.py::test_advected_whenever_g_is_saved",  # 12 s
        "tests/test_contracts.py::test_membership_tolerance_is_the_same_eager_and_traced",  # 12 s
        "tests/test_contracts.py::test_nonfinite_potential_value_is_reported",  # 9 s
        "tests/test_contracts.py::test_parameter_check_eager_and_traced[central-gravity-negative-mu]",  # 23 s
        "tests/test_contracts.py::test_parameter_check_eager_and_traced[se3-indefinite]",  # 39 s
        "tests/test_contracts.py::test_parameter_check_eager_and_traced[uniform-gravity-negative-mass]",  # 8 s
        "tests/test_convergence.py::test_second_order_on_son[dep-exp]",  # 8 s
        "tests/test_conversions.py::test_euler_gradients_finite_at_gimbal_lock[float32]",  # 21 s
        "tests/test_conversions.py::test_euler_gradients_finite_at_gimbal_lock[float64]",  # 16 s
        "tests/test_demo.py::test_demo_in_process_json_and_plot",  # 33 s
        "tests/test_dep.py::test_conservation_generalized_rigid_body[dep-exp]",  # 13 s
        "tests/test_dep.py::test_del_residual_generalized_rigid_body[dep-exp-4]",  # 18 s
        "tests/test_dep.py::test_right_invariant_is_mirrored_left_invariant[dep-exp]",  # 10 s
        "tests/test_forcing.py::test_batch_with_per_body_controls",  # 8 s
        "tests/test_forcing.py::test_zero_forcing_is_the_unforced_run[free-dep-exp]",  # 10 s
        "tests/test_forcing.py::test_zero_forcing_is_the_unforced_run[heavy-top-dep-exp]",  # 9 s
        "tests/test_gradients.py::test_gradient_independent_of_newton_iterations[exp]",  # 14 s
        "tests/test_gradients.py::test_jacfwd_equals_jacrev[exp]",  # 11 s
        "tests/test_group_autodiff.py::test_son_derivatives_are_finite[4]",  # 8 s
        "tests/test_loop.py::test_failure_is_recorded_across_blocks[generic]",  # 10 s
        "tests/test_loop.py::test_simulate_batch_eager_equals_jit[h-per-body-save0-generic]",  # 10 s
        "tests/test_loop.py::test_simulate_batch_eager_equals_jit[h-per-body-save1-generic]",  # 10 s
        "tests/test_loop.py::test_simulate_batch_eager_equals_jit[shared-h-save0-generic]",  # 13 s
        "tests/test_loop.py::test_simulate_batch_eager_equals_jit[shared-h-save1-generic]",  # 9 s
        "tests/test_loop.py::test_simulate_eager_equals_jit[preprocessed-12-3]",  # 8 s
        "tests/test_identification.py::test_batch_shapes_and_report",  # 32 s
        "tests/test_kernel_parity.py::test_batch_equals_reference[composition-splitting-6]",  # 19 s
        "tests/test_kernel_parity.py::test_batch_equals_reference[dep-exp-heavy-top]",  # 18 s
        "tests/test_kernel_parity.py::test_batch_equals_reference[dep-exp-se3]",  # 39 s
        "tests/test_kernel_parity.py::test_batch_equals_reference[dep-exp]",  # 13 s
        "tests/test_kernel_parity.py::test_batch_equals_reference[moser-veselov]",  # 13 s
        "tests/test_kernel_parity.py::test_batch_equals_reference[rk4]",  # 10 s
        "tests/test_kernel_parity.py::test_batch_equals_reference[rkmk4-se3-gravity]",  # 24 s
        "tests/test_kernel_parity.py::test_iterates_and_gradients_equal_reference[composition-dep-4-se3]",  # 75 s
        "tests/test_kernel_parity.py::test_iterates_and_gradients_equal_reference[dep-cayley-heavy-top]",  # 10 s
        "tests/test_kernel_parity.py::test_iterates_and_gradients_equal_reference[dep-cayley]",  # 9 s
        "tests/test_kernel_parity.py::test_iterates_and_gradients_equal_reference[dep-exp-heavy-top]",  # 11 s
        "tests/test_kernel_parity.py::test_iterates_and_gradients_equal_reference[dep-exp-se3]",  # 37 s
        "tests/test_kernel_parity.py::test_iterates_and_gradients_equal_reference[dep-exp]",  # 11 s
        "tests/test_kernel_parity.py::test_iterates_and_gradients_equal_reference[moser-veselov-heavy-top]",  # 9 s
        "tests/test_kernel_parity.py::test_iterates_and_gradients_equal_reference[moser-veselov]",  # 9 s
        "tests/test_kernel_parity.py::test_iterates_and_gradients_equal_reference[rkmk4-se3]",  # 76 s
        "tests/test_kernel_parity.py::test_iterates_and_gradients_equal_reference[rkmk4]",  # 10 s
        "tests/test_kernel_parity.py::test_iterates_and_gradients_equal_reference[splitting-heavy-top]",  # 8 s
        "tests/test_learned_dynamics.py::test_neural_potential_keeps_its_symmetry_and_is_differentiable",  # 16 s
        "tests/test_notebooks.py::test_notebook_runs[01_free_rigid_body.ipynb]",  # 19 s
        "tests/test_notebooks.py::test_notebook_runs[05_heavy_top.ipynb]",  # 32 s
        "tests/test_optimal_control.py::test_sphere_rest_to_rest_matches_the_closed_form",  # 13 s
        "tests/test_potentials.py::test_gradients_match_finite_differences",  # 8 s
        "tests/test_potentials.py::test_potential_on_son",  # 19 s
        "tests/test_potentials.py::test_right_invariant_mirror_image",  # 13 s
        "tests/test_properties.py::test_fast_path_equals_generic_path",  # 9 s
        "tests/test_properties.py::test_scale_invariance_float64",  # 11 s
        "tests/test_reliability.py::test_overridden_step_is_run_on_every_path",  # 8 s
        "tests/test_rigid_bodies.py::test_control_per_body_equals_each_body_alone",  # 14 s
        "tests/test_rigid_bodies.py::test_coupling_evaluated_once_per_step[dep]",  # 25 s
        "tests/test_rigid_bodies.py::test_damping_force_law_per_body",  # 8 s
        "tests/test_rigid_bodies.py::test_gradient_of_coupling_parameter[integrator0]",  # 10 s
        "tests/test_rigid_bodies.py::test_one_body_equals_rigid_body_se3[exp]",  # 30 s
        "tests/test_rigid_bodies.py::test_order[integrator1-molecules-2]",  # 11 s
        "tests/test_rigid_bodies.py::test_reverse_pass_stores_little_per_step[integrator0]",  # 9 s
        "tests/test_rigid_bodies.py::test_simulate_batch_of_systems",  # 10 s
        "tests/test_rigid_bodies.py::test_total_momentum_and_energy[molecules-integrator0]",  # 17 s
        "tests/test_rkmk.py::test_fourth_order_on_se3_through_the_kernel[free]",  # 13 s
        "tests/test_se3_batch.py::test_failures_are_reported_per_body",  # 40 s
        "tests/test_se3_batch.py::test_float32",  # 51 s
        "tests/test_se3_batch.py::test_kernel_converges_where_newton_does[cayley]",  # 15 s
        "tests/test_se3_batch.py::test_kernel_converges_where_newton_does[exp]",  # 21 s
        "tests/test_se3_batch.py::test_stragglers_take_the_gathered_tail[exp]",  # 33 s
        "tests/test_se3_body.py::test_closed_form_step_equals_generic[exp-False]",  # 15 s
        "tests/test_se3_body.py::test_del_residual[exp-falling]",  # 10 s
        "tests/test_se3_body.py::test_del_residual[exp-kirchhoff]",  # 14 s
        "tests/test_se3_body.py::test_dep_second_order[exp-satellite]",  # 22 s
        "tests/test_simulate.py::test_simulate_under_outer_jit_and_vmap",  # 10 s
        "tests/test_stream.py::test_streamed_equals_in_memory[True]",  # 14 s
        "tests/test_suggest.py::test_suggested_step_reaches_the_tolerance[1e-08]",  # 30 s
        "tests/test_simulate.py::test_mixed_precision_promotes[dep]",  # 18 s
        "tests/test_stream.py::test_save_m_only_and_progress",  # 14 s
        # The exp-chart (or one duplicate) variant of checks whose other variants stay in
        # the default suite (`pytest --durations`, on a 2-core machine about 1.7× slower
        # than the one of the figures above):
        "tests/test_dep.py::test_dlp_map_is_poisson[dep-exp]",  # 20 s
        "tests/test_dep.py::test_start_from_two_configurations[dep-exp]",  # 14 s
        "tests/test_dep.py::test_del_residual_hlw[dep-exp]",  # 11 s
        "tests/test_dep.py::test_del_residual_generalized_rigid_body[dep-cayley-4]",  # 9 s
        "tests/test_contracts.py::test_damping_is_unit_invariant[integrator0]",  # 15 s
        "tests/test_forcing.py::test_zero_forcing_is_the_unforced_run[free-splitting]",  # 13 s
        "tests/test_forcing.py::test_zero_forcing_is_the_unforced_run[heavy-top-splitting]",  # 9 s
        "tests/test_forcing.py::test_order_with_a_force_law_and_a_potential[dep-exp]",  # 12 s
        "tests/test_forcing.py::test_damping_decays_to_rest_with_the_work_balance[dep-exp]",  # 10 s
        "tests/test_gradients.py::test_checkpointing_changes_nothing[exp-True]",  # 13 s
        "tests/test_gradients.py::test_gradient_finite_at_zero_momentum_float32[exp]",  # 11 s
        "tests/test_loop.py::test_simulate_eager_equals_jit[DEP-9-1]",  # 12 s
        "tests/test_loop.py::test_simulate_eager_equals_jit[DEP-5-5]",  # 10 s
        "tests/test_convergence.py::test_second_order_on_hlw[dep-exp]",  # 8 s
        "tests/test_se3_batch.py::test_linear_momentum_sets_the_tolerance[exp]",  # 39 s
        "tests/test_se3_body.py::test_kirchhoff_conservation[exp]",  # 23 s
        "tests/test_se3_body.py::test_del_residual[cayley-satellite]",  # 18 s
        "tests/test_simulate.py::test_newton_converges_fast_for_moderate_steps[dep-exp]",  # 13 s
        "tests/test_dep.py::test_batched_equals_per_body[dep-exp]",  # 14 s
        # More variants of checks whose other variants stay in the default suite (the
        # same machine, `pytest --durations=200`):
        "tests/test_loop.py::test_simulate_eager_equals_jit[preprocessed-5-5]",  # 11 s
        "tests/test_loop.py::test_simulate_eager_equals_jit[SE3-RK4-12-3]",  # 10 s
        "tests/test_loop.py::test_simulate_eager_equals_jit[SE3-RK4-5-5]",  # 9 s
        "tests/test_loop.py::test_simulate_batch_eager_equals_jit[h-per-body-save0-fast]",  # 13 s
        "tests/test_loop.py::test_simulate_batch_eager_equals_jit[shared-h-save1-fast]",  # 12 s
        "tests/test_potentials.py::test_zero_potential_is_the_free_body[dep-exp-zero-mass]",  # 12 s
        "tests/test_potentials.py::test_zero_potential_is_the_free_body[moser-veselov-zero-mass]",  # 9 s
        "tests/test_potentials.py::test_second_order_heavy_top[dep-exp]",  # 10 s
        "tests/test_reliability.py::test_tolerance_is_relative_scaled_body_gives_same_trajectory[1e-13-dep-cayley]",  # 5 s
        "tests/test_reliability.py::test_tolerance_is_relative_scaled_body_gives_same_trajectory[1e-13-preprocessed]",  # 5 s
        "tests/test_reliability.py::test_tolerance_is_relative_scaled_body_gives_same_trajectory[1e-13-composition]",  # 4 s
        "tests/test_rkmk.py::test_saves_the_advected_parameter[RKMK8()]",  # 15 s
        "tests/test_rkmk.py::test_stays_on_the_group_where_rk4_drifts[RKMK8()]",  # 8 s
        "tests/test_rkmk.py::test_fourth_order_and_more_accurate_than_embedded_rk4[right]",  # 8 s
        "tests/test_progress.py::test_batch_meter_updates_one_line[False]",  # 13 s
        "tests/test_equivalences.py::test_moser_veselov_iterates_satisfy_5_4[4]",  # 6 s
        # Every check of ≥ 8.5 s left in the default suite when it had grown to 20 minutes
        # (`pytest --durations=150`, the same machine), but the last default case of a
        # check (the DEL residual, orders, the right-invariant mirror, conservation of the
        # full body's spatial momentum, the gradient and implicit-derivative checks against
        # finite differences), one fast-against-reference case, the equivalence theorem,
        # the float32 runs, the bad-input and branch-rule checks, one streamed run and the
        # two-process run:
        "tests/test_rigid_bodies.py::test_coupling_evaluated_once_per_step[splitting-4]",  # 27 s
        "tests/test_optimal_control.py::test_unconverged_solve_is_reported",  # 24 s
        "tests/test_rigid_bodies.py::test_control_per_body_in_a_batch_of_systems",  # 22 s
        "tests/test_se3_body.py::test_free_fall_momenta",  # 21 s
        "tests/test_site_neighbors.py::test_segmented_run_with_forcing",  # 20 s
        "tests/test_group_autodiff.py::test_son_exp_derivative_at_identity_is_the_basis[4]",  # 19 s
        "tests/test_rigid_rotors.py::test_order[integrator0-dipoles-2]",  # 19 s
        "tests/test_stream.py::test_bad_arguments",  # 19 s
        "tests/test_batch.py::test_reduced_heavy_top_equals_reconstructed[dep-exp]",  # 18 s
        "tests/test_simulate.py::test_mixed_precision_promotes[mv]",  # 18 s
        "tests/test_forcing.py::test_gradient_of_a_whole_control_sequence[dep-exp]",  # 18 s
        "tests/test_contracts.py::test_parameter_check_batched_fast_path",  # 17 s
        "tests/test_rigid_rotors.py::test_gradient_of_coupling_parameter[integrator0]",  # 17 s
        "tests/test_rigid_bodies.py::test_total_momentum_and_energy[molecules-integrator1]",  # 17 s
        "tests/test_potentials.py::test_lagrange_top_keeps_its_spin",  # 17 s
        "tests/test_properties.py::test_traced_and_eager_validation_agree",  # 16 s
        "tests/test_rkmk.py::test_order_of_the_tableau[rkmk5]",  # 16 s
        "tests/test_contracts.py::test_vmapped_system_without_system_axis",  # 16 s
        "tests/test_reliability.py::test_prepared_preprocessed_rejects_another_trajectory_and_bad_h",  # 16 s
        "tests/test_batch.py::test_moser_veselov_scalar_solve_at_large_steps",  # 16 s
        "tests/test_contracts.py::test_damping_is_unit_invariant[integrator1]",  # 15 s
        "tests/test_properties.py::test_scale_invariance_float32",  # 15 s
        "tests/test_identification.py::test_default_inertia_estimate",  # 15 s
        "tests/test_stream.py::test_resume_after_a_stop",  # 15 s
        "tests/test_fit_optimizer.py::test_lbfgs_rosenbrock_batch_equals_alone",  # 14 s
        "tests/test_progress.py::test_batch_meter_updates_one_line[True]",  # 14 s
        "tests/test_loop.py::test_simulate_eager_equals_jit[preprocessed-9-1]",  # 14 s
        "tests/test_loop.py::test_simulate_batch_eager_equals_jit[shared-h-save0-fast]",  # 14 s
        "tests/test_se3.py::test_derivatives_finite_at_zero_and_near_pi[f64]",  # 14 s
        "tests/test_rkmk.py::test_fourth_order_on_se3_through_the_kernel[gravity]",  # 14 s
        "tests/test_kernel_parity.py::test_batch_equals_reference[splitting]",  # 14 s
        "tests/test_rigid_rotors.py::test_one_rotor_equals_rigid_body[integrator0]",  # 14 s
        "tests/test_reliability.py::test_tolerance_is_relative_float32_satellite_units[0.0001]",  # 13 s
        "tests/test_loop.py::test_simulate_batch_eager_equals_jit[h-per-body-save1-fast]",  # 13 s
        "tests/test_preprocessed_dmv.py::test_prepared_for_another_step_size",  # 13 s
        "tests/test_forcing.py::test_float32_forced_run",  # 13 s
        "tests/test_gradients.py::test_moser_veselov_gradient_matches_finite_differences",  # 13 s
        "tests/test_kernel_parity.py::test_iterates_and_gradients_equal_reference[rk4]",  # 13 s
        "tests/test_loop.py::test_under_transformations_the_static_scan_is_used",  # 13 s
        "tests/test_rigid_rotors.py::test_simulate_batch_of_systems",  # 13 s
        "tests/test_loop.py::test_simulate_eager_equals_jit[DEP-12-3]",  # 13 s
        "tests/test_rkmk.py::test_fourth_order_heavy_top_with_control",  # 13 s
        "tests/test_forcing.py::test_order_with_a_held_control",  # 12 s
        "tests/test_gradients.py::test_gradient_finite_when_a_step_fails",  # 12 s
        "tests/test_reliability.py::test_log_checked_rejects_non_rotations",  # 12 s
        "tests/test_moser_veselov.py::test_implicit_derivative_matches_finite_differences",  # 12 s
        "tests/test_splitting.py::test_derivative_matches_finite_differences[False]",  # 12 s
        "tests/test_properties.py::test_son_log_is_exact_or_nan_near_half_turns",  # 11 s
        "tests/test_simulate.py::test_newton_converges_fast_for_moderate_steps[dep-cayley]",  # 11 s
        "tests/test_loop.py::test_failure_is_recorded_across_blocks[fast]",  # 11 s
        "tests/test_rkmk.py::test_fourth_order_and_more_accurate_than_embedded_rk4[left]",  # 11 s
        "tests/test_rkmk.py::test_saves_the_advected_parameter[RKMK4()]",  # 11 s
        "tests/test_potentials.py::test_three_d_pendulum",  # 11 s
        "tests/test_moser_veselov.py::test_generalized_rigid_body[4]",  # 11 s
        "tests/test_potentials.py::test_zero_potential_is_the_free_body[dep-exp-zero-callable]",  # 11 s
        "tests/test_dep.py::test_generic_lagrangian_matches_rigid_body[dep-exp]",  # 11 s
        "tests/test_forcing.py::test_order_with_a_force_law_and_a_potential[rk4]",  # 11 s
        "tests/test_rigid_rotors.py::test_free_rotors_keep_each_body_casimir_and_momentum",  # 11 s
        "tests/test_batch.py::test_explicit_step_derivative_rules[3-splitting]",  # 10 s
        "tests/test_potentials.py::test_potential_parameters_under_vmap",  # 10 s
        "tests/test_rigid_rotors.py::test_order[integrator4-alignment-4]",  # 10 s
        "tests/test_simulate.py::test_save_every_and_times",  # 10 s
        "tests/test_potentials.py::test_start_from_two_configurations",  # 10 s
        "tests/test_site_neighbors.py::test_segmented_run_equals_all_pairs_run",  # 10 s
        "tests/test_so3.py::test_son3_coordinates_are_so3_coordinates",  # 10 s
        "tests/test_preprocessed_dmv.py::test_structure_over_1000_steps",  # 10 s
        "tests/test_preprocessed_dmv.py::test_full_inertia_tensor_equals_principal_frame",  # 10 s
        "tests/test_reliability.py::test_son4_near_half_turns_exact",  # 10 s
        "tests/test_forcing.py::test_zero_forcing_is_the_unforced_run[free-rk4]",  # 10 s
        "tests/test_dep.py::test_son3_generalized_body_matches_rigid_body",  # 10 s
        "tests/test_batch.py::test_batched_equals_per_body[dep-exp]",  # 10 s
        "tests/test_simulate.py::test_failure_in_a_batch_is_per_body",  # 9 s
        "tests/test_forcing.py::test_forced_discrete_noether_per_step[dep-exp]",  # 9 s
        "tests/test_son.py::test_hat_vee_and_basis[8]",  # 9 s
        "tests/test_frames.py::test_angular_velocity_matches_the_motion_of_g",  # 9 s
        "tests/test_son.py::test_hat_vee_and_basis[4]",  # 9 s
        "tests/test_batch.py::test_shared_system_and_save_options",  # 9 s
        "tests/test_loop.py::test_simulate_eager_equals_jit[SE3-RK4-9-1]",  # 9 s
        "tests/test_dep.py::test_generalized_rigid_body_increments_that_need_scaling",  # 50 s
        # The documentation's examples (tests/test_docs_examples.py) whose pages compile
        # fits, coupled bodies or SE(3) programs; the quick-start pages stay by default:
        "tests/test_docs_examples.py::test_page_examples_run[docs/identification.md]",  # 70 s
        "tests/test_docs_examples.py::test_page_examples_run[docs/rigid-bodies.md]",  # 67 s
        "tests/test_docs_examples.py::test_page_examples_run[docs/optimal-control.md]",  # 58 s
        "tests/test_docs_examples.py::test_page_examples_run[docs/gradients.md]",  # 40 s
        "tests/test_docs_examples.py::test_page_examples_run[docs/forcing.md]",  # 55 s
        "tests/test_docs_examples.py::test_page_examples_run[docs/se3.md]",  # 24 s
        "tests/test_docs_examples.py::test_page_examples_run[docs/potentials.md]",  # 22 s
        "tests/test_docs_examples.py::test_page_examples_run[docs/preprocessed_dmv.md]",  # 15 s
        "tests/test_docs_examples.py::test_cluster_script_in_two_processes[False]",  # 72 s
        # The module fixture (a batched fit, 65 s) and the three checks that read it:
        "tests/test_identification.py::test_hlw_noise_free_recovers_moments",
        "tests/test_identification.py::test_hlw_noisy_recovers_moments",
        "tests/test_identification.py::test_random_bodies_noise_free",
    }
)
# SO(n) for n = 5, 6, 7: the generic operators compile once per n (6–9 s each on this
# machine); n = 2, 3, 4 and 8 stay in the default suite, the smallest cases and the largest.
EXTENDED_SON = ("[5]", "[6]", "[7]")


def pytest_collection_modifyitems(config, items):
    for item in items:
        son = item.nodeid.startswith("tests/test_son.py::") and item.nodeid.endswith(EXTENDED_SON)
        if item.nodeid in EXTENDED or son:
            item.add_marker(pytest.mark.extended)
