#!/usr/bin/env bash
# Regenerate docs/cli.md from `boostnerf COMMAND --help` (tests/test_docs.py checks it is in step).
set -euo pipefail
cd "$(dirname "$0")/.."
{
  echo "# Command reference"; echo
  echo "Generated from \`boostnerf COMMAND --help\` by scripts/cli-reference.sh (a test checks that each section is the command's \`--help\` as printed now)."; echo
  echo "\`boostnerf --version\` prints the version. A mistake on the command line (an unknown option, a value of the wrong type, a missing option) is one line starting \`error:\` that names the command's \`--help\`, exit code 2, as every other refusal is."; echo
  echo "## \`boostnerf\`: options of every command"; echo
  echo "These go before the command: \`boostnerf -q pretrain ...\`, \`boostnerf -v finetune ...\`. A warning is a line starting \`warning:\` on stderr, said also under \`-q\`; the tables and files written go to stdout."; echo
  echo '```'
  COLUMNS=100 boostnerf --help 2>&1 | sed 's/[[:space:]]*$//'
  echo '```'; echo
  for c in make-scene pretrain build-moe finetune render camera-path eval count-params export chain prune bench view capture; do
    echo "## \`boostnerf $c\`"; echo; echo '```'
    COLUMNS=100 boostnerf "$c" --help 2>&1 | sed 's/[[:space:]]*$//'
    echo '```'; echo
  done
} > docs/cli.md
