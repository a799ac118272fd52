"""Reports read from run folders and studies: ``curves`` (learning curves), ``plots`` (figures),
``accuracy_report`` (what accuracy costs in time), ``choices`` (the axes and bands a figure offers)."""
