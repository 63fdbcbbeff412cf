"""Statistics (ANOVA, EMMs, assumption checks), the HTML report, figures and videos."""
