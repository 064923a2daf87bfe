# Two commands do everything: `make demo` and `make test` (each creates .venv if missing).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: install demo test bench reports clean

$(BIN)/d2a: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -c constraints.txt -e ".[test,ray]"
	touch $(BIN)/d2a

install: $(BIN)/d2a

demo: install
	$(BIN)/d2a demo

test: install
	$(BIN)/python -m pytest -q

bench: install
	$(BIN)/d2a bench envs

# Rewrite every report in docs/ from the cells stored there (nothing is trained or evaluated); a grid
# first copies in the cells of its plan that another grid finished under the same name (--shared-cells).
OTHER_ROWS := --demos 10 --task stick-pull --task push --task lever-pull --task assembly --task hammer \
	--algo edm --algo cp --algo flowpolicy --algo dp --algo mp1 --algo dp3
TABLE1_CELLS := --shared-cells docs/table1/points128/cells
TABLE4_CELLS := --shared-cells docs/table4/points128/cells
OTHER_CELLS := --shared-cells docs/other_methods/cells
reports: install
	$(BIN)/d2a bench table1 --report --policy-points 128 --results docs/table1/points128 $(TABLE4_CELLS) $(OTHER_CELLS)
	$(BIN)/d2a bench table4 --report --policy-points 128 --results docs/table4/points128 $(TABLE1_CELLS) $(OTHER_CELLS)
	$(BIN)/d2a bench table4 --report --policy-points 128 $(OTHER_ROWS) --results docs/other_methods $(TABLE1_CELLS) \
		$(TABLE4_CELLS)
	$(BIN)/d2a bench table4 --report --policy-points 128 --demos 1 --demos 2 --task push --algo d2a-present \
		--algo d2a-oracle --results docs/table4/oracle128
	$(BIN)/d2a bench table4 --report --policy-points 128 --demos 2 --demos 5 --task stick-pull --task push \
		--algo d2a --algo d2a-present --wm-without-actions --results docs/table4/noactions128
	$(BIN)/d2a bench table4 --report --policy-points 128 --demos 2 --task lever-pull --algo d2a --algo d2a-present \
		--wm-rollouts 20 --wm-policy-rollouts d2a --results docs/table4/policyrollouts128
	$(BIN)/d2a bench table4 --report --policy-points 128 --demos 2 --task push --demo-seed 1000 --algo d2a \
		--algo d2a-present --algo mp1 --results docs/table4/pool1000
	$(BIN)/d2a bench table4 --report --policy-points 128 --demos 2 --task push --demo-seed 2000 --algo d2a \
		--algo d2a-present --seed 0 --seed 1 --seed 2 --seed 3 --seed 4 --results docs/table4/pool2000
	$(BIN)/d2a bench table4 --report --policy-points 256 --demos 5 --task stick-pull --algo mp1 \
		--results docs/table4/points256
	$(BIN)/d2a bench paired --results docs/table1/points128 --results docs/table4/points128 --results docs/table4 \
		--markdown docs/imagination_pairs.md --plot docs/imagination_pairs.png
	$(BIN)/d2a bench order --results docs/other_methods --order dp cp dp3 flowpolicy mp1 \
		--markdown docs/other_methods/ordering.md --plot docs/other_methods/ordering.png

clean:
	rm -rf $(VENV) *.egg-info
