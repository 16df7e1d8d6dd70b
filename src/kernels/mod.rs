pub mod xfeat;
