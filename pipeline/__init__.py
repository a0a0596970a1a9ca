"""pgnn-feedforward: data-driven feedforward control with physics-guided neural networks."""
