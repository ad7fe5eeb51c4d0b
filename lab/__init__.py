"""cerpe's development studies: run from the checkout as ``python -m lab.NAME`` (see lab/README.md).

Not part of the installed package: each study measures something on development data
(never the paper-default suite) and prints it; none is a product command.
"""
