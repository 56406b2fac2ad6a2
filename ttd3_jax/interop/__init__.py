"""The policy and the env outside this package (layer 5): the exported policy (``policy``: ONNX,
a C header and ``policy.json``), Gymnasium and gymnax front ends of the env (``adapters``), and
Brax's own trainers on JAX 0.10 (``brax_compat``)."""
