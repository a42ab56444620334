from recon3d.cli import main

main()
