"""The paper's studies on the embedded eel FOM: pipeline, figures, report, reference numbers."""
