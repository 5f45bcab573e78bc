"""Integration: RK4, the stepper, the step-size policy, observers, the host driver and the differentiable solve. Imports only `jaxsleigh.model` and the base modules."""
