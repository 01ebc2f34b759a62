"""The web console: one page that shows the live pipeline and controls it."""
