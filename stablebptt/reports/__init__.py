"""Reports read from run folders and studies: ``curves`` (learning curves), ``plots`` (figures),
``accuracy_report`` (what accuracy costs in time)."""
