"""The geometry and model core: poses and the noise model (metres, REP 103), frames and scene objects,
object models, rendering, the BOP pose-error metrics and plots."""
