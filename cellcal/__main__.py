from cellcal.cli import main

main()
