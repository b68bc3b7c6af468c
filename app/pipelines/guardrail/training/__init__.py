"""Training the guardrail slice classifier: samples from simulated surveys (`dataset`), the
heads' fitting and the model card (`train`). The only guardrail code that imports the simulator."""
